"""Progress: per batch and per worker for the staff pages, and what the annotator's page shows of theirs."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime
from typing import Any

from sqlalchemy import and_, case, func, or_, select

from core.db import db, utcnow

from .models import Aggregate, Answer, Batch, BatchItem, CrowdSession, Reservation, Worker
from .queries import ANSWER_COUNT, as_utc, run_prebuilt, worker_id_of
from .workers import gold_label


def answer_count(worker: Worker | int, session: int | None = None) -> int:
    """How many answers the worker has stored in ``session`` (the progress its page shows)."""
    return run_prebuilt(ANSWER_COUNT, {"worker_id": worker_id_of(worker), "session_id": session}).scalar() or 0


def batch_positions(worker: Worker | int, batch_ids: Iterable[int]) -> dict[int, dict[str, int]]:
    """Per batch: ``done`` (this worker's answers in it, every session) and ``total`` (done plus
    the items still open to them: regular items below N usable answers that they have not
    answered, and gold items they hold). ``total`` can shrink while they work, as others finish
    items; it never counts an item twice. Two grouped reads, whatever the batch size.
    """
    worker_id, ids = worker_id_of(worker), sorted(set(batch_ids))
    if not ids:
        return {}
    done = dict(
        db.session.execute(
            select(BatchItem.batch_id, func.count())
            .join(Answer, Answer.item_id == BatchItem.id)
            .where(Answer.worker_id == worker_id, BatchItem.batch_id.in_(ids))
            .group_by(BatchItem.batch_id)
        ).all()
    )
    answered = select(Answer.id).where(Answer.item_id == BatchItem.id, Answer.worker_id == worker_id).exists()
    holds = (
        select(Reservation.id)
        .where(Reservation.item_id == BatchItem.id, Reservation.worker_id == worker_id, Reservation.answered_at.is_(None))
        .exists()
    )
    open_ = dict(
        db.session.execute(
            select(BatchItem.batch_id, func.count())
            .join(Batch, Batch.id == BatchItem.batch_id)
            .where(
                BatchItem.batch_id.in_(ids),
                ~answered,
                or_(
                    and_(BatchItem.is_gold.is_(False), BatchItem.answers < Batch.answers_per_item),
                    and_(BatchItem.is_gold.is_(True), holds),
                ),
            )
            .group_by(BatchItem.batch_id)
        ).all()
    )
    return {b: {"done": int(done.get(b, 0)), "total": int(done.get(b, 0)) + int(open_.get(b, 0))} for b in ids}


def batch_progress(batch: Batch, now: datetime | None = None) -> dict[str, Any]:
    """Done / reserved / expired counts for a batch and per worker, with each worker's gold score in it.

    Per worker: ``done`` answers, open ``reserved`` and lapsed ``expired`` reservations,
    ``gold_correct`` of ``gold_total`` gold answers (see :func:`annotation.workers.gold_label`) and ``flagged``
    answers (given while or before the worker fell below the gold threshold).
    """
    now = now or utcnow()
    items = {it.id: it for it in batch.items}
    regular = sum(1 for it in items.values() if not it.is_gold)
    answers = list(
        db.session.execute(
            select(Answer.item_id, Answer.worker_id, Answer.payload, Answer.flagged).where(Answer.item_id.in_(list(items)))
        )
    )
    reservations = list(
        db.session.execute(
            select(Reservation.worker_id, Reservation.expires_at).where(
                Reservation.item_id.in_(list(items)), Reservation.answered_at.is_(None)
            )
        )
    )
    per_worker: dict[int, dict[str, int]] = {}

    def row(worker_id: int) -> dict[str, int]:
        return per_worker.setdefault(
            worker_id, {"done": 0, "reserved": 0, "expired": 0, "gold_correct": 0, "gold_total": 0, "flagged": 0}
        )

    for item_id, worker_id, payload, flagged in answers:
        counts = row(worker_id)
        counts["done"] += 1
        counts["flagged"] += bool(flagged)
        item = items[item_id]
        if item.is_gold and item.gold_answer:
            counts["gold_total"] += 1
            counts["gold_correct"] += gold_label(batch.kind, payload, item.gold_answer)
    reserved = expired = 0
    for worker_id, expires_at in reservations:
        key = "reserved" if as_utc(expires_at) > now else "expired"
        row(worker_id)[key] += 1
        reserved += key == "reserved"
        expired += key == "expired"
    # What the batch still needs: usable answers on regular items, at most N per item (answers
    # on gold items and flagged answers fill no slot; an item can briefly hold more than N).
    usable: dict[int, int] = {}
    for item_id, _worker, _payload, flagged in answers:
        if not flagged and not items[item_id].is_gold:
            usable[item_id] = usable.get(item_id, 0) + 1
    n = batch.answers_per_item
    return {
        "batch": batch.id,
        "kind": batch.kind,
        "items": regular,
        "gold_items": len(items) - regular,
        "answers_per_item": n,
        "answers": len(answers),
        "regular_answers": sum(min(c, n) for c in usable.values()),
        "gold_answers": sum(1 for a in answers if items[a[0]].is_gold),
        "flagged_answers": sum(1 for a in answers if a[3]),
        "items_done": sum(1 for c in usable.values() if c >= n),
        "answers_needed": regular * batch.answers_per_item,
        "reserved": reserved,
        "expired": expired,
        "workers": {str(w): counts for w, counts in sorted(per_worker.items())},
    }


# A worker who agrees with the crowd's answer on fewer than this share of at least
# AGREEMENT_MIN_ANSWERS answers is marked on the staff page (never flagged by it: the crowd's
# answer can be wrong, and careful workers on hard cards disagree too).
LOW_AGREEMENT = 0.5
AGREEMENT_MIN_ANSWERS = 5


def crowd_agreement() -> dict[int, list[int]]:
    """Per worker, for each of their answers on a regular item the crowd's answer was reached for
    (an aggregate, approved or waiting for a curator): 1 when it matches that answer, by the rule
    gold uses (:func:`annotation.workers.gold_label`; a question the crowd left undecided is not
    compared), else 0.

    Gold answers are few (a worker meets each gold card once, and one draw in several is gold),
    so a worker can answer a whole batch before gold can judge them: the demo's spammer met one
    gold card in seven answers. Agreement with the crowd needs no gold: a coin-flipping judge
    agrees on all four questions about one time in sixteen.
    """
    out: dict[int, list[int]] = {}
    for worker_id, payload, label, kind in db.session.execute(
        select(Answer.worker_id, Answer.payload, Aggregate.label, Batch.kind)
        .join(BatchItem, Answer.item_id == BatchItem.id)
        .join(Batch, BatchItem.batch_id == Batch.id)
        .join(Aggregate, and_(Aggregate.batch_id == BatchItem.batch_id, Aggregate.card_id == BatchItem.card_id))
        .where(BatchItem.is_gold.is_(False))
    ):
        decided = {key: value for key, value in (label or {}).items() if value is not None}
        if not decided or not isinstance(payload, dict):
            continue
        try:
            out.setdefault(worker_id, []).append(gold_label(kind, payload, decided))
        except (KeyError, TypeError, ValueError):
            continue  # a label without the fields this answer gives (an older aggregate's shape)
    return out


def worker_progress() -> list[dict[str, Any]]:
    """Every worker across batches: answers, flagged answers, gold accuracy and whether they are flagged.

    ``gold_accuracy`` is None until the worker answered a gold item; ``served`` is False once
    they fell below the threshold (they get no more tasks). ``sessions`` is how many visits
    (Prolific sessions, MTurk assignments) they opened, ``completed_sessions`` how many reached
    the completion step, ``refused_sessions`` how many got no work from the start (opened where
    a worker flagged in the same study came from; :mod:`annotation.sessions`).
    """
    sessions = {
        worker_id: (total, completed or 0, refused or 0)
        for worker_id, total, completed, refused in db.session.execute(
            select(
                CrowdSession.worker_id,
                func.count(),
                func.sum(case((CrowdSession.completed_at.is_not(None), 1), else_=0)),
                func.sum(case((CrowdSession.flagged, 1), else_=0)),
            ).group_by(CrowdSession.worker_id)
        )
    }
    counts = {
        worker_id: (total, flagged or 0)
        for worker_id, total, flagged in db.session.execute(
            select(Answer.worker_id, func.count(), func.sum(case((Answer.flagged, 1), else_=0))).group_by(Answer.worker_id)
        )
    }
    gold: dict[int, list[int]] = {}
    for worker_id, payload, gold_answer, kind in db.session.execute(
        select(Answer.worker_id, Answer.payload, BatchItem.gold_answer, Batch.kind)
        .join(BatchItem, Answer.item_id == BatchItem.id)
        .join(Batch, BatchItem.batch_id == Batch.id)
        .where(BatchItem.is_gold.is_(True))
    ):
        if gold_answer:
            gold.setdefault(worker_id, []).append(gold_label(kind, payload, gold_answer))
    agreement = crowd_agreement()
    rows = []
    for worker in db.session.scalars(select(Worker).order_by(Worker.id)):
        total, flagged = counts.get(worker.id, (0, 0))
        opened, completed, refused = sessions.get(worker.id, (0, 0, 0))
        labels = gold.get(worker.id, [])
        agreed = agreement.get(worker.id, [])
        rows.append(
            {
                "worker": worker.id,
                "provider": worker.provider,
                "name": worker.external_id,
                "answers": int(total),
                "flagged_answers": int(flagged),
                "gold_correct": sum(labels),
                "gold_total": len(labels),
                "gold_accuracy": round(sum(labels) / len(labels), 4) if labels else None,
                "agreed": sum(agreed),
                "compared": len(agreed),
                "agreement": round(sum(agreed) / len(agreed), 4) if agreed else None,
                "served": not worker.flagged,
                "sessions": int(opened),
                "completed_sessions": int(completed),
                "refused_sessions": int(refused),
            }
        )
    return rows
