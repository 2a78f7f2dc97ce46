"""The grader's database side: which thresholds are active, and refitting them to curators or to
the true error measured by ``keystone bench grade``.

The thresholds themselves and the fitting are pure (:mod:`pipeline.grading`); this module
reads curator labels and grade measurements, and stores fitted thresholds as a
:class:`review.models.GradeModel` row (the newest row is active).
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import select

from core.audit import record_event
from core.db import db

from .models import GRADES, CardReview, GradeModel
from .report import LABELLED_DECISIONS


class GradingError(Exception):
    """Refitting cannot be done (too few labels, one class only); the message says why."""


def active_grade_params() -> tuple[Any, GradeModel | None]:
    """The grade stage's parameters: the newest fitted thresholds, else the defaults."""
    from pipeline.grading import GradeParams, GradeThresholds

    model = db.session.scalars(select(GradeModel).order_by(GradeModel.id.desc()).limit(1)).first()
    if model is None:
        return GradeParams(), None
    return GradeParams(thresholds=GradeThresholds.from_dict(model.thresholds)), model


def labelled_measurements() -> list[tuple[dict[str, Any], str]]:
    """(grade measurements, curator grade) for every card a curator graded and the grader measured."""
    from core.models import StageResult

    labels = {
        r.card_id: r.grade
        for r in db.session.scalars(
            select(CardReview).where(CardReview.decision.in_(LABELLED_DECISIONS), CardReview.grade.in_(GRADES))
        )
    }
    latest: dict[int, dict[str, Any]] = {}
    for result in db.session.scalars(
        select(StageResult)
        .where(StageResult.stage == "grade", StageResult.status == "done", StageResult.card_id.in_(labels))
        .order_by(StageResult.id)
    ):
        latest[result.card_id] = result.metrics.get("measurements", result.metrics)
    return [(latest[card_id], labels[card_id]) for card_id in sorted(latest)]


def fit_from_curators(*, folds: int = 5, seed: int = 0, save: bool = True, actor: Any = None) -> dict[str, Any]:
    """Fit thresholds to the curator labels; report held-out agreement; save unless told not to."""
    rows = labelled_measurements()
    return _fit_and_store(
        rows, source="curators", why=f"refitted on {len(rows)} curator labels", folds=folds, seed=seed, save=save, actor=actor
    )


def fit_from_bench(
    document: Any,
    *,
    few_below: float = 25.0,
    failure_above: float = 50.0,
    folds: int = 5,
    seed: int = 0,
    save: bool = True,
    actor: Any = None,
) -> dict[str, Any]:
    """Fit thresholds to the true error of ``keystone bench grade --json`` output (``document``:
    the parsed JSON): each graded card's measurements, labelled few / some / failure by its true
    bad-2 (under ``few_below`` %, over ``failure_above`` %, between); report held-out agreement
    with those labels; save unless told not to. Raises :class:`GradingError` for a document
    that is not a bench result or has too few cards."""
    from pipeline.errors import PipelineError
    from pipeline.grading import TrueErrorBands, labels_from_true_error

    if not isinstance(document, dict) or not isinstance(document.get("results"), list):
        raise GradingError("not a `keystone bench grade --json` document: expected an object with a results list")
    try:
        bands = TrueErrorBands(few_below, failure_above)
        rows = labels_from_true_error(document["results"], bands)
    except PipelineError as exc:
        raise GradingError(str(exc)) from exc
    out = _fit_and_store(
        rows,
        source="bench grade (true bad-2)",
        why=f"refitted on {len(rows)} bench cards by true bad-2 (few < {few_below:g} %, failure > {failure_above:g} %)",
        folds=folds,
        seed=seed,
        save=save,
        actor=actor,
    )
    out["bands"] = {"few_below": few_below, "failure_above": failure_above}
    return out


def _fit_and_store(
    rows: list[tuple[Any, str]], *, source: str, why: str, folds: int, seed: int, save: bool, actor: Any
) -> dict[str, Any]:
    from pipeline.errors import PipelineError
    from pipeline.grading import fit_thresholds

    base, _ = active_grade_params()
    try:
        report = fit_thresholds(rows, base.thresholds, folds=folds, seed=seed)
    except PipelineError as exc:
        raise GradingError(str(exc)) from exc
    document = report.as_dict()
    document["labels"] = len(rows)
    document["source"] = source
    document["model"] = None
    if save:
        model = GradeModel(
            thresholds=report.thresholds.to_dict(),
            fitted_on=len(rows),
            evaluation={**document["held_out"], "source": source},
            created_by=getattr(actor, "id", None),
        )
        db.session.add(model)
        db.session.flush()
        record_event(
            entity="grade_model",
            entity_id=model.id,
            action="fit",
            actor=actor,
            actor_label=None if actor else "keystone grade fit",
            before={"thresholds": base.thresholds.to_dict()},
            after={"thresholds": model.thresholds},
            why=why,
        )
        db.session.commit()
        document["model"] = model.id
    return document
