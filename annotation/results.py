"""Results: a batch's answers aggregated (Dawid-Skene per question, box consensus) and its agreement figures."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import select

from core.db import db

from . import questions as question_table
from .aggregation import (
    HALVES,
    ConfidenceRules,
    Judgement,
    JudgementAnswer,
    aggregate_judgements,
    consensus_box,
    unconfident_reasons,
)
from .agreement import gwet_ac1, krippendorff_alpha_boxes, krippendorff_alpha_nominal, percent_agreement
from .confirm import FLAGS as CONFIRM_FLAGS, TapAnswer, aggregate_taps, apply_taps
from .models import Aggregate, Answer, Batch, BatchItem
from .task_errors import TaskError
from .workers import update_worker_quality


@dataclass(frozen=True)
class AggregationReport:
    batch_id: int
    approved: int
    needs_curator: int
    pending: int  # items with fewer than N usable answers
    flagged_workers: int
    agreement: dict[str, dict[str, float | None]] = field(default_factory=dict)
    escalated: int = 0  # confirm cards the grid could not agree on: they go to judge tasks

    def as_json(self) -> dict[str, Any]:
        return {
            "batch": self.batch_id,
            "approved": self.approved,
            "needs_curator": self.needs_curator,
            "escalated": self.escalated,
            "pending": self.pending,
            "flagged_workers": self.flagged_workers,
            "agreement": self.agreement,
        }


def _figure(compute: Any, *args: Any, **kwargs: Any) -> float | None:
    """An agreement figure, or None where it is undefined (too few units, one category only)."""
    try:
        value = float(compute(*args, **kwargs))
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return None
    return round(value, 6) if math.isfinite(value) else None


def batch_agreement(kind: str, answers: Sequence[Answer], items: Iterable[int]) -> dict[str, dict[str, float | None]]:
    """Raw agreement, Krippendorff's alpha and Gwet's AC1 per judge question (non-gold items);
    alpha with 1 - IoU distance per crop half. Why all three: see :mod:`annotation.agreement`.
    """
    item_ids = sorted(set(items))
    if kind in ("judge", "confirm"):
        workers = sorted({a.worker_id for a in answers})
        column, row = {it: j for j, it in enumerate(item_ids)}, {w: i for i, w in enumerate(workers)}
        out: dict[str, dict[str, float | None]] = {}
        table = question_table.grid_questions() if kind == "confirm" else question_table.judge_questions()
        for q in question_table.keys(question_table.asked(table, (a.payload for a in answers))):
            R = np.full((len(workers), len(item_ids)), np.nan)
            for a in answers:
                if a.item_id in column and q in a.payload:
                    R[row[a.worker_id], column[a.item_id]] = float(bool(a.payload[q]))
            out[q] = {
                "percent_agreement": _figure(percent_agreement, R),
                "krippendorff_alpha": _figure(krippendorff_alpha_nominal, R),
                "gwet_ac1": _figure(gwet_ac1, R, n_categories=2),
            }
        return out
    wanted = set(item_ids)
    units: dict[str, dict[int, list[list[float]]]] = {h: {} for h in HALVES}
    for a in answers:
        if a.item_id in wanted:
            for h in HALVES:
                units[h].setdefault(a.item_id, []).append(a.payload[h])
    return {
        h: {"krippendorff_alpha": _figure(krippendorff_alpha_boxes, [np.array(u) for u in units[h].values()])} for h in HALVES
    }


def _judgement(payload: Mapping[str, Any]) -> Judgement:
    """A stored judge answer (or gold answer) as a :class:`Judgement`; a question not asked is absent."""
    return Judgement(
        {q.key: bool(payload[q.key]) for q in question_table.judge_questions() if not q.optional or q.key in payload}
    )


def _confirm_results(
    items: Mapping[int, BatchItem], finished: Sequence[BatchItem], answers: Sequence[Answer], rules: ConfidenceRules
) -> dict[int, tuple[dict[str, Any], dict[str, Any], tuple[str, ...]]]:
    """Per finished confirm item: the posterior of each flag's MAP (tapped or not), the label
    (what was shown, what the crowd tapped, and the orientation that makes: shown XOR tapped)
    and why it waits for a curator."""
    votes = aggregate_taps(
        [TapAnswer(a.item_id, a.worker_id, a.payload) for a in answers],
        {it.id: it.gold_answer for it in items.values() if it.is_gold and it.gold_answer},
    )
    out = {}
    for it in finished:
        tapped = {flag: bool(votes[flag].label_of(it.id)) for flag in CONFIRM_FLAGS}
        sure = {flag: float(votes[flag].posterior(it.id)[int(tapped[flag])]) for flag in CONFIRM_FLAGS}
        shown = {flag: bool((it.shown or {}).get(flag, False)) for flag in CONFIRM_FLAGS}
        label = {**apply_taps(shown, tapped), "shown": shown, "tapped": tapped}
        out[it.id] = ({f: round(p, 6) for f, p in sure.items()}, label, unconfident_reasons(sure, rules=rules))
    return out


def aggregate_batch(batch_id: int, rules: ConfidenceRules | None = None) -> AggregationReport:
    """Flag workers on gold, then aggregate every finished item and store approved / needs_curator.

    Judge: one binary Dawid-Skene per question of :data:`annotation.questions.JUDGE` seeded with
    the batch's gold; when the crowd says "not a stereo pair" (a ``gate`` question), the other
    questions are moot and do not block approval.
    Crop: :func:`consensus_box` per half in original pixels. Confirm: one binary Dawid-Skene
    per flag over the taps (:func:`annotation.confirm.aggregate_taps`).
    """
    rules = rules or ConfidenceRules()
    batch = db.session.get(Batch, batch_id)
    if batch is None:
        raise TaskError(f"No batch {batch_id}", 404)
    quality = update_worker_quality()
    items = {it.id: it for it in batch.items}
    answers = list(db.session.scalars(select(Answer).where(Answer.item_id.in_(list(items)), Answer.flagged.is_(False))))
    by_item: dict[int, list[Answer]] = {}
    for answer in answers:
        by_item.setdefault(answer.item_id, []).append(answer)
    finished = [it for it in items.values() if not it.is_gold and len(by_item.get(it.id, [])) >= batch.answers_per_item]
    pending = sum(1 for it in items.values() if not it.is_gold) - len(finished)
    results: dict[int, tuple[dict[str, Any], dict[str, Any], tuple[str, ...]]] = {}
    if batch.kind == "judge" and finished:
        judged = [JudgementAnswer(a.item_id, a.worker_id, _judgement(a.payload)) for a in answers]
        gold = {it.id: _judgement(it.gold_answer) for it in items.values() if it.is_gold and it.gold_answer}
        table = question_table.judge_questions()
        ds = aggregate_judgements(judged, gold, questions=table)
        for it in finished:
            # An optional question (swapped) only where this card's answers asked it (older pages did not).
            here = question_table.asked(table, (a.payload for a in by_item[it.id]))
            label = {q.key: bool(ds[q.key].label_of(it.id)) for q in here}
            posterior = {q.key: [round(float(p), 6) for p in ds[q.key].posterior(it.id)] for q in here}
            # A gate answered "no" (not a stereo pair) makes the other questions moot.
            closed = [q for q in here if q.gate and not label[q.key]]
            deciding = [q.key for q in (closed or here)]
            reasons = unconfident_reasons({q: float(ds[q].posterior(it.id)[int(label[q])]) for q in deciding}, rules=rules)
            results[it.id] = (posterior, label, reasons)
    elif batch.kind == "confirm" and finished:
        results = _confirm_results(items, finished, answers, rules)
    elif batch.kind == "crop":
        for it in finished:
            card = it.card
            consensus = {
                h: consensus_box([a.payload[h] for a in by_item[it.id]], image_size=(card.width, card.height)) for h in HALVES
            }
            label = {h: [round(v, 2) for v in c.box] for h, c in consensus.items()}
            posterior = {
                h: {"kept": c.kept, "dropped": c.dropped, "mad": list(c.mad), "mean_iou": c.mean_iou}
                for h, c in consensus.items()
            }
            results[it.id] = (posterior, label, unconfident_reasons(boxes=consensus, rules=rules))
    approved = needs = escalated = 0
    for item_id, (posterior, label, reasons) in results.items():
        it = items[item_id]
        row = db.session.scalar(select(Aggregate).where(Aggregate.batch_id == batch.id, Aggregate.card_id == it.card_id))
        if row is not None and row.resolved_by is not None:
            # A curator's decision is the card's truth: re-aggregating never overwrites it.
            approved += 1
            continue
        if row is None:
            row = Aggregate(batch_id=batch.id, card_id=it.card_id, kind=batch.kind)
            db.session.add(row)
        row.posterior, row.label, row.confident = posterior, label, not reasons
        # A grid that cannot agree sends its card to a judge task, not to a curator's queue.
        row.state = "approved" if not reasons else "escalated" if batch.kind == "confirm" else "needs_curator"
        row.reasons, row.answers = "; ".join(reasons), len(by_item[item_id])
        approved += not reasons
        needs += bool(reasons) and batch.kind != "confirm"
        escalated += bool(reasons) and batch.kind == "confirm"
    db.session.commit()
    regular = [it.id for it in items.values() if not it.is_gold]
    return AggregationReport(
        batch.id,
        approved,
        needs,
        pending,
        sum(1 for q in quality.values() if q["flagged"]),
        batch_agreement(batch.kind, answers, regular),
        escalated,
    )
