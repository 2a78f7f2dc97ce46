"""Figures for ``keystone report`` and the report page: grades per collection beside the
paper's, agreement of the automatic grades with curators, and crowd agreement per batch.

Read-only: everything is computed from the catalogue in one deferred transaction.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from typing import Any

from sqlalchemy import select

from core.db import db, read_only
from core.models import Card, Collection, StageResult

from .models import GRADES, CardReview, GradeModel

# KeystoneDepth's manual grading of a 711-card sample (paper, Sec. 4): few / some / failure.
PAPER_DISTRIBUTION: dict[str, float] = {"few": 0.23, "some": 0.49, "failure": 0.28}
PAPER_SAMPLE = 711
# Decisions where a curator set the card's grade: the labels the grader is judged against.
LABELLED_DECISIONS = ("accepted", "changed")


def _fractions(counts: dict[str, int]) -> dict[str, float | None]:
    total = sum(counts.values())
    return {g: (round(counts.get(g, 0) / total, 4) if total else None) for g in GRADES}


def latest_auto_grades() -> dict[int, str]:
    """card id -> outcome of the card's most recent ``grade`` result that is done."""
    rows = db.session.execute(
        select(StageResult.card_id, StageResult.outcome)
        .where(StageResult.stage == "grade", StageResult.status == "done")
        .order_by(StageResult.card_id, StageResult.id)
    )
    return {card_id: outcome for card_id, outcome in rows if outcome in GRADES}


def agreement(pairs: list[tuple[str, str]]) -> dict[str, Any]:
    """Confusion matrix (rows = curator label, columns = automatic grade, order few/some/failure),
    accuracy, Cohen's kappa, macro-F1 and per-class precision/recall of the automatic grade."""
    # pipeline.grade_agreement, not pipeline.grading: that package imports SciPy (1.5-3 s the first
    # time a server process drew this page).
    from pipeline.grade_agreement import agreement as grade_agreement

    index = {g: i for i, g in enumerate(GRADES)}
    return grade_agreement([index[truth] for truth, _ in pairs], [index[auto] for _, auto in pairs], GRADES)


def label_sources(reviews: list[Any], auto: dict[int, str]) -> dict[str, int]:
    """What the agreement is computed from: per decision, the cards with an automatic grade and a
    curator's grade. An accepted card's grade *is* its automatic grade (agreement by construction);
    only changed cards can disagree. Rejected, sent-back and pending cards carry no grade label."""
    counted = Counter(r.decision for r in reviews if r.decision in LABELLED_DECISIONS and r.grade and r.card_id in auto)
    return {decision: counted.get(decision, 0) for decision in LABELLED_DECISIONS}


def crowd_agreement() -> list[dict[str, Any]]:
    """Agreement figures per crowd batch (raw, Krippendorff's alpha, Gwet's AC1 where defined)."""
    from annotation.models import Answer, Batch, BatchItem
    from annotation.results import batch_agreement

    batches = list(db.session.scalars(select(Batch).order_by(Batch.id)))
    out = []
    for batch in batches:
        items = [row for row in db.session.scalars(select(BatchItem).where(BatchItem.batch_id == batch.id))]
        regular = [it.id for it in items if not it.is_gold]
        answers = list(
            db.session.scalars(
                select(Answer).join(BatchItem, Answer.item_id == BatchItem.id).where(BatchItem.batch_id == batch.id)
            )
        )
        out.append(
            {
                "batch": batch.id,
                "kind": batch.kind,
                "items": len(regular),
                "answers": len(answers),
                "agreement": batch_agreement(batch.kind, [a for a in answers if a.item_id in set(regular)], regular),
            }
        )
    return out


def build_report() -> dict[str, Any]:
    """The whole report as one JSON-safe document."""
    with read_only():
        auto = latest_auto_grades()
        reviews = {r.card_id: r for r in db.session.scalars(select(CardReview))}
        collections = {c.id: c.name for c in db.session.scalars(select(Collection))}
        card_collection = dict(db.session.execute(select(Card.id, Card.collection_id)).all())
        per_collection: dict[int, dict[str, Any]] = defaultdict(
            lambda: {"cards": 0, "auto": Counter(), "final": Counter(), "decisions": Counter()}
        )
        for card_id, collection_id in card_collection.items():
            entry = per_collection[collection_id]
            entry["cards"] += 1
            if card_id in auto:
                entry["auto"][auto[card_id]] += 1
            review = reviews.get(card_id)
            entry["decisions"][review.decision if review else "not reviewed"] += 1
            if review is not None and review.decision in LABELLED_DECISIONS and review.grade:
                entry["final"][review.grade] += 1
        pairs = [
            (r.grade, auto[r.card_id])
            for r in reviews.values()
            if r.decision in LABELLED_DECISIONS and r.grade and r.card_id in auto
        ]
        model = db.session.scalars(select(GradeModel).order_by(GradeModel.id.desc()).limit(1)).first()
        crowd = crowd_agreement()

    collections_out = []
    for collection_id, entry in sorted(per_collection.items()):
        collections_out.append(
            {
                "collection": collections.get(collection_id, str(collection_id)),
                "cards": entry["cards"],
                "automatic": {"counts": {g: entry["auto"].get(g, 0) for g in GRADES}, "fractions": _fractions(entry["auto"])},
                "curated": {"counts": {g: entry["final"].get(g, 0) for g in GRADES}, "fractions": _fractions(entry["final"])},
                "decisions": dict(sorted(entry["decisions"].items())),
            }
        )
    return {
        "paper": {"fractions": PAPER_DISTRIBUTION, "sample": PAPER_SAMPLE},
        "collections": collections_out,
        "automatic_vs_curator": {**agreement(pairs), "labels_from": label_sources(list(reviews.values()), auto)},
        "grade_model": None
        if model is None
        else {
            "id": model.id,
            "fitted_on": model.fitted_on,
            "created_at": model.created_at.isoformat(),
            "held_out": model.evaluation,
        },
        "crowd": crowd,
    }


def plot_distribution(report: dict[str, Any]) -> bytes:
    """PNG bar chart: automatic and curated grade fractions per collection beside the paper's."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    series = [("paper (711 cards)", PAPER_DISTRIBUTION)]
    for entry in report["collections"]:
        for kind in ("automatic", "curated"):
            if any(entry[kind]["counts"].values()):
                series.append((f"{entry['collection']}: {kind}", entry[kind]["fractions"]))
    figure = Figure(figsize=(7, 0.5 + 0.45 * len(series)), dpi=100)
    axes = figure.add_subplot()
    colours = {"few": "#3a7d44", "some": "#e0a526", "failure": "#b8383b"}
    for row, (label, fractions) in enumerate(series):
        left = 0.0
        for grade in GRADES:
            width = fractions.get(grade) or 0.0
            axes.barh(row, width, left=left, color=colours[grade], label=grade if row == 0 else None)
            if width >= 0.06:
                axes.text(left + width / 2, row, f"{width:.0%}", ha="center", va="center", color="white", fontsize=8)
            left += width
    axes.set_yticks(range(len(series)), [label for label, _ in series], fontsize=8)
    axes.invert_yaxis()
    axes.set_xlim(0, 1)
    axes.set_xlabel("fraction of graded cards")
    axes.legend(loc="lower right", fontsize=8, ncols=3)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", metadata={"Software": None})
    return buffer.getvalue()


def plot_confusion(report: dict[str, Any]) -> bytes:
    """PNG heat map of the automatic grade against curator labels (counts in the cells)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    block = report["automatic_vs_curator"]
    figure = Figure(figsize=(4, 3.4), dpi=100)
    axes = figure.add_subplot()
    axes.imshow(block["confusion"], cmap="Blues")
    for i, row in enumerate(block["confusion"]):
        for j, value in enumerate(row):
            axes.text(j, i, str(value), ha="center", va="center", fontsize=10)
    axes.set_xticks(range(3), GRADES)
    axes.set_yticks(range(3), GRADES)
    axes.set_xlabel("automatic grade")
    axes.set_ylabel("curator")
    kappa = block["cohen_kappa"]
    axes.set_title(f"{block['labels']} labels, kappa {kappa if kappa is not None else 'n/a'}", fontsize=9)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", metadata={"Software": None})
    return buffer.getvalue()
