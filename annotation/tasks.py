"""Use cases: the pure strategy (assignment, aggregation) mapped onto crowd rows.

Every function here runs inside the caller's app context and commits its own transaction.
Errors a worker can cause are :class:`TaskError` with an HTTP status and a sentence for them.
"""

from __future__ import annotations

import math
import secrets
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np
from flask import current_app
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError

from app.db import db, utcnow
from app.models import Card

from . import assignment as strategy
from .aggregation import (
    QUESTIONS,
    ConfidenceRules,
    InvalidBoxError,
    Judgement,
    JudgementAnswer,
    LabelAnswer,
    aggregate_judgements,
    box_iou,
    consensus_box,
    flag_workers,
    gold_accuracy,
    unconfident_reasons,
    validate_box,
)
from .agreement import (
    gwet_ac1,
    krippendorff_alpha_boxes,
    krippendorff_alpha_nominal,
    percent_agreement,
)
from .models import TASK_KINDS, Aggregate, Answer, Batch, BatchItem, Reservation, Worker

DEFAULT_RESERVATION_MINUTES = 10
DEFAULT_MIN_BOX_PX = 16
DEFAULT_GOLD_THRESHOLD = 0.7
DEFAULT_MIN_GOLD = 3
HALVES: tuple[str, ...] = ("left", "right")


class TaskError(Exception):
    """Something the worker (or an admin) did wrong: shown to them, status for the HTTP reply."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.message = message
        self.status = status


def _config(name: str, default: Any) -> Any:
    return current_app.config.get(name, default)


def _aware(moment: datetime) -> datetime:
    # SQLite hands back naive datetimes for DateTime(timezone=True); they were stored as UTC.
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


# ---------------------------------------------------------------------------------------------
# Batches and workers


def create_batch(card_ids: Sequence[int], kind: str = "judge", n: int = 3, gold_rate: float = 0.1, *,
                 gold: Mapping[int, dict[str, Any]] | None = None, created_by: int | None = None) -> Batch:
    """A batch over ``card_ids`` plus the gold cards in ``gold`` (card id -> known answer)."""
    if kind not in TASK_KINDS:
        raise TaskError(f"Expected kind judge or crop, got {kind!r}")
    if n < 1:
        raise TaskError(f"Expected at least 1 answer per item, got {n}")
    if not 0.0 <= gold_rate <= 1.0:
        raise TaskError(f"Expected 0 <= gold rate <= 1, got {gold_rate}")
    gold = dict(gold or {})
    wanted = list(dict.fromkeys([*card_ids, *gold]))
    if not wanted:
        raise TaskError("Expected at least one card, got none")
    found = set(db.session.scalars(select(Card.id).where(Card.id.in_(wanted))))
    missing = [c for c in wanted if c not in found]
    if missing:
        raise TaskError(f"No card with id {', '.join(map(str, missing))}", 404)
    cards = {c.id: c for c in db.session.scalars(select(Card).where(Card.id.in_(wanted)))}
    for card_id, answer in gold.items():
        validate_payload(kind, answer, cards[card_id])
    batch = Batch(kind=kind, answers_per_item=n, gold_rate=gold_rate, created_by=created_by)
    for card_id in wanted:
        batch.items.append(BatchItem(card_id=card_id, is_gold=card_id in gold, gold_answer=gold.get(card_id)))
    db.session.add(batch)
    db.session.commit()
    return batch


def review_queue_card_ids() -> list[int]:
    """Cards the filter sent to human judgement (state ``review``)."""
    return list(db.session.scalars(select(Card.id).where(Card.state == "review").order_by(Card.id)))


def get_or_create_worker(provider: str, external_id: str, person_id: int | None = None) -> Worker:
    """Find the worker by (provider, external id) or make one; a race is settled by the unique key."""
    query = select(Worker).where(Worker.provider == provider, Worker.external_id == external_id)
    worker = db.session.scalar(query)
    if worker is not None:
        return worker
    worker = Worker(provider=provider, external_id=external_id, person_id=person_id,
                    token=secrets.token_urlsafe(24))
    db.session.add(worker)
    try:
        db.session.commit()
    except IntegrityError:
        db.session.rollback()
        worker = db.session.scalar(query)
        assert worker is not None
    return worker


# ---------------------------------------------------------------------------------------------
# Fetching a task


@dataclass(frozen=True)
class Task:
    reservation_token: str
    batch_id: int
    kind: str
    card_id: int
    card_size: tuple[int, int]  # (width, height) of the original, the frame of crop boxes
    expires_at: datetime

    def as_json(self) -> dict[str, Any]:
        return {"token": self.reservation_token, "batch": self.batch_id, "kind": self.kind,
                "card_width": self.card_size[0], "card_height": self.card_size[1],
                "expires_at": self.expires_at.isoformat()}


def _task(reservation: Reservation) -> Task:
    item, card = reservation.item, reservation.item.card
    return Task(reservation.token, item.batch_id, item.batch.kind, card.id, (card.width, card.height),
                _aware(reservation.expires_at))


def open_reservations(worker: Worker, now: datetime) -> list[Reservation]:
    rows = db.session.scalars(
        select(Reservation).where(Reservation.worker_id == worker.id, Reservation.answered_at.is_(None))
        .order_by(Reservation.created_at, Reservation.id))
    return [r for r in rows if _aware(r.expires_at) > now]


def _policy(batch: Batch) -> strategy.AssignmentPolicy:
    minutes = float(_config("KEYSTONE_CROWD_RESERVATION_MINUTES", DEFAULT_RESERVATION_MINUTES))
    return strategy.AssignmentPolicy(answers_per_item=batch.answers_per_item, gold_rate=batch.gold_rate,
                                     reservation_ttl=timedelta(minutes=minutes), seed=batch.id)


def _reserve_in_batch(batch: Batch, worker: Worker, now: datetime) -> strategy.Assignment | strategy.NoTask:
    items = list(db.session.scalars(select(BatchItem).where(BatchItem.batch_id == batch.id)))
    item_ids = [it.id for it in items]
    # Reservations before answers: under READ COMMITTED (PostgreSQL) a submit may commit
    # between the two reads. In this order it is seen twice (held, then answered), a harmless
    # over-count; in the other order it would be seen nowhere and its slot handed out again.
    holds = [
        strategy.Reservation(r.item_id, r.worker_id, _aware(r.expires_at))
        for r in db.session.scalars(select(Reservation).where(
            Reservation.item_id.in_(item_ids), Reservation.answered_at.is_(None)))
    ]
    answered: dict[int, set[int]] = {}
    for item_id, worker_id in db.session.execute(
            select(Answer.item_id, Answer.worker_id).where(Answer.item_id.in_(item_ids))):
        answered.setdefault(item_id, set()).add(worker_id)
    return strategy.next_assignment(
        [strategy.BatchItem(it.id, frozenset(answered.get(it.id, ()))) for it in items],
        holds, {it.id for it in items if it.is_gold}, worker.id, now,
        policy=_policy(batch), flagged_workers={worker.id} if worker.flagged else frozenset())


def next_tasks(worker: Worker, kind: str = "judge", hold: int = 2,
               now: datetime | None = None) -> tuple[list[Task], strategy.NoTask | None]:
    """The worker's open tasks, topping up to ``hold`` of them (the second is preloaded by the page).

    Runs in one write transaction (SQLite: BEGIN IMMEDIATE; PostgreSQL: the batches are locked
    FOR UPDATE) so two workers asking at once see each other's reservations and N is never
    exceeded. Returns the tasks oldest first and, when fewer than ``hold``, why there are no more.
    """
    now = now or utcnow()
    worker = db.session.get(Worker, worker.id, populate_existing=True)  # fresh flag inside the transaction
    assert worker is not None
    held = [r for r in open_reservations(worker, now) if r.item.batch.kind == kind]
    why: strategy.NoTask | None = None
    if len(held) < hold:
        batches = list(db.session.scalars(select(Batch).where(Batch.kind == kind).order_by(Batch.id).with_for_update()))
        while len(held) < hold:
            chosen: tuple[Batch, strategy.Assignment] | None = None
            for batch in batches:
                result = _reserve_in_batch(batch, worker, now)
                if isinstance(result, strategy.Assignment):
                    chosen = (batch, result)
                    break
                if why is None or result.reason != strategy.NoTaskReason.BATCH_COMPLETE:
                    why = result
            if chosen is None:
                break
            held.append(_store_reservation(int(chosen[1].item_id), worker.id, chosen[1].expires_at))
        if why is None and not batches:
            why = strategy.NoTask(strategy.NoTaskReason.BATCH_COMPLETE)
    tasks = [_task(r) for r in held]
    db.session.commit()
    return tasks, (why if len(tasks) < hold else None)


def _store_reservation(item_id: int, worker_id: int, expires_at: datetime) -> Reservation:
    # A lapsed reservation of the same worker on the same item is renewed, not duplicated.
    row = db.session.scalar(select(Reservation).where(Reservation.item_id == item_id,
                                                      Reservation.worker_id == worker_id))
    if row is None:
        row = Reservation(item_id=item_id, worker_id=worker_id, token=secrets.token_urlsafe(24),
                          expires_at=expires_at)
        db.session.add(row)
    else:
        row.expires_at, row.answered_at, row.created_at = expires_at, None, utcnow()
    db.session.flush()
    return row


def reservation_by_token(token: str) -> Reservation | None:
    return db.session.scalar(select(Reservation).where(Reservation.token == token))


# ---------------------------------------------------------------------------------------------
# Answers


def _as_bool(payload: Mapping[str, Any], key: str) -> bool:
    value = payload.get(key)
    if not isinstance(value, bool):
        raise TaskError(f"Expected {key} to be true or false, got {value!r}")
    return value


def _as_box(value: Any, half: str, card: Card) -> list[float]:
    if not isinstance(value, list) or len(value) != 4 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise TaskError(f"Expected the {half} box as four numbers [x0, y0, x1, y1], got {value!r}")
    try:
        box = validate_box(value, (card.width, card.height))
    except InvalidBoxError as exc:
        raise TaskError(f"The {half} box is refused: {exc}") from exc
    minimum = int(_config("KEYSTONE_CROWD_MIN_BOX_PX", DEFAULT_MIN_BOX_PX))
    if box[2] - box[0] < minimum or box[3] - box[1] < minimum:
        raise TaskError(f"The {half} box is refused: it must be at least {minimum} x {minimum} pixels, "
                        f"got {box[2] - box[0]:g} x {box[3] - box[1]:g}")
    return [round(v, 2) for v in box]


def validate_payload(kind: str, payload: Any, card: Card) -> dict[str, Any]:
    """The canonical answer, or TaskError saying what is wrong with it.

    judge: ``{"is_stereo", "upside_down", "inverted"}`` booleans. crop: ``{"left", "right"}``
    boxes ``[x0, y0, x1, y1]`` in original image pixels, inside the card, at least the minimum size.
    """
    if not isinstance(payload, dict):
        raise TaskError(f"Expected a JSON object as the answer, got {type(payload).__name__}")
    expected = set(QUESTIONS) if kind == "judge" else set(HALVES)
    extra = sorted(set(payload) - expected)
    if extra:
        raise TaskError(f"Unexpected fields in the answer: {', '.join(extra)}")
    if kind == "judge":
        return {q: _as_bool(payload, q) for q in QUESTIONS}
    return {half: _as_box(payload.get(half), half, card) for half in HALVES}


@dataclass(frozen=True)
class Submitted:
    answer_id: int
    duplicate: bool  # True when this post repeated an answer already stored


def submit(worker: Worker, reservation_token: str, payload: Any, idempotency_key: str,
           now: datetime | None = None) -> Submitted:
    """Store one answer for an open reservation of ``worker``; replays return the stored one."""
    now = now or utcnow()
    if not isinstance(idempotency_key, str) or not 8 <= len(idempotency_key) <= 80:
        raise TaskError("Expected an idempotency key of 8 to 80 characters")
    earlier = db.session.scalar(select(Answer).where(Answer.idempotency_key == idempotency_key))
    if earlier is not None:
        if earlier.worker_id != worker.id:
            raise TaskError("This idempotency key belongs to another answer", 409)
        db.session.rollback()
        return Submitted(earlier.id, True)
    reservation = reservation_by_token(reservation_token) if isinstance(reservation_token, str) else None
    if reservation is None:
        raise TaskError("No such task; fetch a new one", 404)
    if reservation.worker_id != worker.id:
        raise TaskError("This task is reserved for another worker", 403)
    if reservation.answered_at is not None:
        raise TaskError("You already answered this task", 409)
    if _aware(reservation.expires_at) <= now:
        raise TaskError(f"Your reservation of this task expired at {_aware(reservation.expires_at):%H:%M:%S} UTC; "
                        "fetch a new task", 409)
    item = reservation.item
    answer = validate_payload(item.batch.kind, payload, item.card)
    row = Answer(item_id=item.id, worker_id=worker.id, payload=answer, submitted_at=now,
                 idempotency_key=idempotency_key, flagged=worker.flagged)
    reservation.answered_at = now
    db.session.add(row)
    try:
        db.session.commit()
    except IntegrityError:
        # A double click that raced past the checks: the unique (item, worker) keeps one answer.
        db.session.rollback()
        stored = db.session.scalar(select(Answer).where(Answer.item_id == item.id, Answer.worker_id == worker.id))
        if stored is None:
            raise
        return Submitted(stored.id, True)
    if item.is_gold:
        update_worker_quality([worker.id])
    return Submitted(row.id, False)


def undo_last(worker: Worker, now: datetime | None = None) -> Task:
    """Withdraw the worker's latest answer while it is not aggregated; its task is reserved again."""
    now = now or utcnow()
    last = db.session.scalar(select(Answer).where(Answer.worker_id == worker.id)
                             .order_by(Answer.submitted_at.desc(), Answer.id.desc()).limit(1))
    if last is None:
        raise TaskError("There is no answer to undo", 409)
    aggregated = db.session.scalar(select(func.count()).select_from(Aggregate).where(
        Aggregate.batch_id == last.item.batch_id, Aggregate.card_id == last.item.card_id))
    if aggregated:
        raise TaskError("That answer was already counted in the results and cannot be undone", 409)
    batch = last.item.batch
    item_id = last.item_id
    db.session.delete(last)
    reservation = _store_reservation(item_id, worker.id, now + _policy(batch).reservation_ttl)
    task = _task(reservation)
    db.session.commit()
    return task


# ---------------------------------------------------------------------------------------------
# Quality and aggregation


def _gold_label(kind: str, answer: Mapping[str, Any], gold: Mapping[str, Any]) -> int:
    """1 when the answer matches gold: all three judgements, or both boxes at IoU >= 0.5."""
    if kind == "judge":
        return int(all(bool(answer[q]) == bool(gold[q]) for q in QUESTIONS))
    return int(all(box_iou(answer[h], gold[h])[0, 0] >= 0.5 for h in HALVES))


def update_worker_quality(worker_ids: Iterable[int] | None = None) -> dict[int, dict[str, Any]]:
    """Gold accuracy per worker; those below the threshold are flagged with all their answers."""
    query = select(Answer, BatchItem, Batch).join(BatchItem, Answer.item_id == BatchItem.id).join(
        Batch, BatchItem.batch_id == Batch.id).where(BatchItem.is_gold.is_(True))
    if worker_ids is not None:
        query = query.where(Answer.worker_id.in_(list(worker_ids)))
    labels = [LabelAnswer(item.id, answer.worker_id, _gold_label(batch.kind, answer.payload, item.gold_answer or {}))
              for answer, item, batch in db.session.execute(query)]
    scores = gold_accuracy(labels, {a.item_id: 1 for a in labels})
    threshold = float(_config("KEYSTONE_CROWD_GOLD_THRESHOLD", DEFAULT_GOLD_THRESHOLD))
    flagged = flag_workers(scores, threshold, int(_config("KEYSTONE_CROWD_MIN_GOLD", DEFAULT_MIN_GOLD)))
    for worker_id in flagged:
        worker = db.session.get(Worker, worker_id)
        if worker is not None and not worker.flagged:
            worker.flagged = True
            for answer in db.session.scalars(select(Answer).where(Answer.worker_id == worker_id)):
                answer.flagged = True
            # Their open reservations go back to the pool at once.
            db.session.execute(delete(Reservation).where(Reservation.worker_id == worker_id,
                                                         Reservation.answered_at.is_(None)))
    db.session.commit()
    return {int(w): {"correct": s.correct, "total": s.total, "accuracy": s.accuracy, "flagged": w in flagged}
            for w, s in scores.items()}


@dataclass(frozen=True)
class AggregationReport:
    batch_id: int
    approved: int
    needs_curator: int
    pending: int  # items with fewer than N usable answers
    flagged_workers: int
    agreement: dict[str, dict[str, float | None]] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        return {"batch": self.batch_id, "approved": self.approved, "needs_curator": self.needs_curator,
                "pending": self.pending, "flagged_workers": self.flagged_workers, "agreement": self.agreement}


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
    if kind == "judge":
        workers = sorted({a.worker_id for a in answers})
        column, row = {it: j for j, it in enumerate(item_ids)}, {w: i for i, w in enumerate(workers)}
        out: dict[str, dict[str, float | None]] = {}
        for q in QUESTIONS:
            R = np.full((len(workers), len(item_ids)), np.nan)
            for a in answers:
                if a.item_id in column:
                    R[row[a.worker_id], column[a.item_id]] = float(bool(a.payload[q]))
            out[q] = {"percent_agreement": _figure(percent_agreement, R),
                      "krippendorff_alpha": _figure(krippendorff_alpha_nominal, R),
                      "gwet_ac1": _figure(gwet_ac1, R, n_categories=2)}
        return out
    wanted = set(item_ids)
    units: dict[str, dict[int, list[list[float]]]] = {h: {} for h in HALVES}
    for a in answers:
        if a.item_id in wanted:
            for h in HALVES:
                units[h].setdefault(a.item_id, []).append(a.payload[h])
    return {h: {"krippendorff_alpha": _figure(krippendorff_alpha_boxes, [np.array(u) for u in units[h].values()])}
            for h in HALVES}


def aggregate_batch(batch_id: int, rules: ConfidenceRules | None = None) -> AggregationReport:
    """Flag workers on gold, then aggregate every finished item and store approved / needs_curator.

    Judge: one binary Dawid-Skene per question seeded with the batch's gold; when the crowd
    says "not a stereo pair", orientation and inversion are moot and do not block approval.
    Crop: :func:`consensus_box` per half in original pixels.
    """
    rules = rules or ConfidenceRules()
    batch = db.session.get(Batch, batch_id)
    if batch is None:
        raise TaskError(f"No batch {batch_id}", 404)
    quality = update_worker_quality()
    items = {it.id: it for it in batch.items}
    answers = list(db.session.scalars(select(Answer).where(Answer.item_id.in_(list(items)),
                                                           Answer.flagged.is_(False))))
    by_item: dict[int, list[Answer]] = {}
    for answer in answers:
        by_item.setdefault(answer.item_id, []).append(answer)
    finished = [it for it in items.values()
                if not it.is_gold and len(by_item.get(it.id, [])) >= batch.answers_per_item]
    pending = sum(1 for it in items.values() if not it.is_gold) - len(finished)
    results: dict[int, tuple[dict[str, Any], dict[str, Any], tuple[str, ...]]] = {}
    if batch.kind == "judge" and finished:
        judged = [JudgementAnswer(a.item_id, a.worker_id, Judgement(**{q: bool(a.payload[q]) for q in QUESTIONS}))
                  for a in answers]
        gold = {it.id: Judgement(**{q: bool(it.gold_answer[q]) for q in QUESTIONS})
                for it in items.values() if it.is_gold and it.gold_answer}
        ds = aggregate_judgements(judged, gold)
        for it in finished:
            label = {q: bool(ds[q].label_of(it.id)) for q in QUESTIONS}
            posterior = {q: [round(float(p), 6) for p in ds[q].posterior(it.id)] for q in QUESTIONS}
            asked = QUESTIONS if label["is_stereo"] else ("is_stereo",)
            reasons = unconfident_reasons({q: float(ds[q].posterior(it.id)[int(label[q])]) for q in asked},
                                          rules=rules)
            results[it.id] = (posterior, label, reasons)
    elif batch.kind == "crop":
        for it in finished:
            card = it.card
            consensus = {h: consensus_box([a.payload[h] for a in by_item[it.id]], image_size=(card.width, card.height))
                         for h in HALVES}
            label = {h: [round(v, 2) for v in c.box] for h, c in consensus.items()}
            posterior = {h: {"kept": c.kept, "dropped": c.dropped, "mad": list(c.mad), "mean_iou": c.mean_iou}
                         for h, c in consensus.items()}
            results[it.id] = (posterior, label, unconfident_reasons(boxes=consensus, rules=rules))
    approved = needs = 0
    for item_id, (posterior, label, reasons) in results.items():
        it = items[item_id]
        row = db.session.scalar(select(Aggregate).where(Aggregate.batch_id == batch.id,
                                                        Aggregate.card_id == it.card_id))
        if row is None:
            row = Aggregate(batch_id=batch.id, card_id=it.card_id, kind=batch.kind)
            db.session.add(row)
        row.posterior, row.label, row.confident = posterior, label, not reasons
        row.state = "approved" if not reasons else "needs_curator"
        row.reasons, row.answers = "; ".join(reasons), len(by_item[item_id])
        approved += not reasons
        needs += bool(reasons)
    db.session.commit()
    regular = [it.id for it in items.values() if not it.is_gold]
    return AggregationReport(batch.id, approved, needs, pending, sum(1 for q in quality.values() if q["flagged"]),
                             batch_agreement(batch.kind, answers, regular))


def batch_progress(batch: Batch, now: datetime | None = None) -> dict[str, Any]:
    """Done / reserved / expired counts for a batch and per worker."""
    now = now or utcnow()
    item_ids = [it.id for it in batch.items]
    regular = sum(1 for it in batch.items if not it.is_gold)
    answers = list(db.session.execute(select(Answer.item_id, Answer.worker_id).where(Answer.item_id.in_(item_ids))))
    reservations = list(db.session.scalars(select(Reservation).where(Reservation.item_id.in_(item_ids),
                                                                     Reservation.answered_at.is_(None))))
    per_worker: dict[int, dict[str, int]] = {}
    for _item, worker_id in answers:
        per_worker.setdefault(worker_id, {"done": 0, "reserved": 0, "expired": 0})["done"] += 1
    reserved = expired = 0
    for r in reservations:
        key = "reserved" if _aware(r.expires_at) > now else "expired"
        per_worker.setdefault(r.worker_id, {"done": 0, "reserved": 0, "expired": 0})[key] += 1
        reserved += key == "reserved"
        expired += key == "expired"
    return {"batch": batch.id, "kind": batch.kind, "items": regular, "gold_items": len(item_ids) - regular,
            "answers_per_item": batch.answers_per_item, "answers": len(answers),
            "answers_needed": regular * batch.answers_per_item, "reserved": reserved, "expired": expired,
            "workers": {str(w): counts for w, counts in sorted(per_worker.items())}}

