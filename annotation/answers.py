"""Answers: validating a payload, submitting it for an open reservation, undoing the latest one.

Every function here runs inside the caller's app context and commits its own transaction.
Errors a worker can cause are :class:`annotation.task_errors.TaskError`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any, NamedTuple

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError

from core.db import db, one_writer, read_only, utcnow
from core.models import Card

from . import questions as question_table
from .aggregation import HALVES, InvalidBoxError, validate_box
from .crowd_settings import min_box_px, reservation_ttl
from .models import Aggregate, Answer, Worker
from .queries import (
    ANSWER_BY_KEY,
    CLAIM_RESERVATION,
    INSERT_ANSWER,
    LOCK_ITEMS,
    RESERVATION_STATE,
    RESERVATION_TO_ANSWER,
    WORKER_FLAGGED,
    as_utc,
    on_sqlite,
    recount_items,
    run_prebuilt,
    worker_id_of,
)
from .reservations import Task, store_reservation, task_of
from .task_errors import TaskError
from .workers import update_worker_quality


class CardSize(NamedTuple):
    """What answer validation needs of a card: the original's size in pixels (a Card also fits)."""

    width: int
    height: int


def _as_bool(payload: Mapping[str, Any], key: str) -> bool:
    value = payload.get(key)
    if not isinstance(value, bool):
        raise TaskError(f"Expected {key} to be true or false, got {value!r}")
    return value


# How each answer type of the question table (annotation.questions) is checked and stored.
ANSWER_CHECKS = {"yes_no": _as_bool}


def _answers_to(questions: tuple[question_table.Question, ...], payload: Mapping[str, Any]) -> dict[str, Any]:
    """The answer to each question of ``questions`` (an optional one only where given), or TaskError."""
    extra = sorted(set(payload) - set(question_table.keys(questions)))
    if extra:
        raise TaskError(f"Unexpected fields in the answer: {', '.join(map(str, extra))[:200]}")
    return {q.key: ANSWER_CHECKS[q.answer](payload, q.key) for q in questions if not q.optional or q.key in payload}


def _as_box(value: Any, half: str, card: Card | CardSize) -> list[float]:
    if (
        not isinstance(value, list)
        or len(value) != 4
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        raise TaskError(f"Expected the {half} box as four numbers [x0, y0, x1, y1], got {value!r}")
    try:
        box = validate_box(value, (card.width, card.height))
    except InvalidBoxError as exc:
        raise TaskError(f"The {half} box is refused: {exc}") from exc
    minimum = min_box_px()
    if box[2] - box[0] < minimum or box[3] - box[1] < minimum:
        raise TaskError(
            f"The {half} box is refused: it must be at least {minimum} x {minimum} pixels, "
            f"got {box[2] - box[0]:g} x {box[3] - box[1]:g}"
        )
    return [round(v, 2) for v in box]


def validate_payload(kind: str, payload: Any, card: Card | CardSize) -> dict[str, Any]:
    """The canonical answer, or TaskError saying what is wrong with it.

    judge: one answer per question of :data:`annotation.questions.JUDGE` under its key
    (``is_stereo``, ``upside_down``, ``inverted`` booleans, and ``swapped``, the photos in the
    wrong eye order, where the page asked it: an optional question is stored only when given, so
    aggregation can tell "not asked" from "no"). crop: ``{"left", "right"}`` boxes ``[x0, y0,
    x1, y1]`` in original image pixels, inside the card, at least the minimum size. confirm: one
    boolean per question of :data:`annotation.questions.GRID` (``upside_down``, ``inverted``,
    ``swapped``), true where the worker tapped it (it looked wrong).
    """
    if not isinstance(payload, dict):
        raise TaskError(f"Expected a JSON object as the answer, got {type(payload).__name__}")
    if kind == "confirm":
        return _answers_to(question_table.grid_questions(), payload)
    if kind == "judge":
        return _answers_to(question_table.judge_questions(), payload)
    extra = sorted(set(payload) - set(HALVES))
    if extra:
        raise TaskError(f"Unexpected fields in the answer: {', '.join(extra)}")
    return {half: _as_box(payload.get(half), half, card) for half in HALVES}


@dataclass(frozen=True)
class Submitted:
    answer_id: int
    duplicate: bool  # True when this post repeated an answer already stored


def submit(
    worker: Worker | int,
    reservation_token: str,
    payload: Any,
    idempotency_key: str,
    now: datetime | None = None,
    session: int | None = None,
) -> Submitted:
    """Store one answer for an open reservation of ``worker`` in ``session``; replays return the stored one.

    Checks and validation run in a read transaction; the write transaction only claims the
    reservation (an UPDATE that matches while it is still open), inserts the answer and
    recounts the item.
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    if not isinstance(idempotency_key, str) or not 8 <= len(idempotency_key) <= 80:
        raise TaskError("Expected an idempotency key of 8 to 80 characters")
    with read_only():
        earlier = _answer_by_key(idempotency_key, worker_id, session)
        if earlier is not None:
            return earlier
        held = (
            run_prebuilt(RESERVATION_TO_ANSWER, {"token": reservation_token}).first()
            if isinstance(reservation_token, str)
            else None
        )
        _check_reservation(held, worker_id, session, now)
        answer = validate_payload(held.kind, payload, CardSize(held.width, held.height))
        flagged = bool(run_prebuilt(WORKER_FLAGGED, {"worker_id": worker_id, "session_id": session}).scalar())
    try:
        with one_writer():
            if not on_sqlite():
                run_prebuilt(LOCK_ITEMS, {"item_ids": [held.item_id]})
            claimed = run_prebuilt(
                CLAIM_RESERVATION, {"reservation_id": held.id, "claimant": worker_id, "claimant_session": session, "at": now}
            )
            if claimed.rowcount == 1:
                answer_id = run_prebuilt(
                    INSERT_ANSWER,
                    {
                        "item_id": held.item_id,
                        "worker_id": worker_id,
                        "session_id": session,
                        "payload": answer,
                        "submitted_at": now,
                        "idempotency_key": idempotency_key,
                        "flagged": flagged,
                    },
                ).inserted_primary_key[0]
                recount_items([held.item_id], locked=True)
                db.session.commit()
            else:
                db.session.rollback()
    except IntegrityError:
        # A replay that raced past the checks: the unique key and (item, worker) keep one answer.
        db.session.rollback()
        with read_only():
            stored = db.session.scalar(select(Answer.id).where(Answer.item_id == held.item_id, Answer.worker_id == worker_id))
        if stored is None:
            raise
        return Submitted(stored, True)
    if claimed.rowcount != 1:
        # Answered (a double click with another key, a second tab) or withdrawn (the worker was
        # flagged) since the read: say which, as a fresh read would.
        with read_only():
            earlier = _answer_by_key(idempotency_key, worker_id, session)
            if earlier is not None:
                return earlier
            _check_reservation(run_prebuilt(RESERVATION_STATE, {"reservation_id": held.id}).first(), worker_id, session, now)
        raise TaskError("This task changed while you answered; fetch a new one", 409)
    if held.is_gold:
        update_worker_quality([worker_id])
    return Submitted(int(answer_id), False)


def _answer_by_key(idempotency_key: str, worker_id: int, session: int | None) -> Submitted | None:
    earlier = run_prebuilt(ANSWER_BY_KEY, {"key": idempotency_key}).first()
    if earlier is None:
        return None
    if earlier.worker_id != worker_id or earlier.session_id != session:
        raise TaskError("This idempotency key belongs to another answer", 409)
    return Submitted(earlier.id, True)


def _check_reservation(held: Any, worker_id: int, session: int | None, now: datetime) -> None:
    """TaskError unless ``held`` (a reservation row) is an open task of this worker's session."""
    if held is None:
        raise TaskError("No such task; fetch a new one", 404)
    if held.worker_id != worker_id:
        raise TaskError("This task is reserved for another worker", 403)
    if held.session_id != session:
        raise TaskError("This task belongs to another session; fetch a new one", 403)
    if held.answered_at is not None:
        raise TaskError("You already answered this task", 409)
    if as_utc(held.expires_at) <= now or held.released_at is not None:
        raise TaskError(f"Your reservation of this task expired at {as_utc(held.expires_at):%H:%M:%S} UTC; fetch a new task", 409)


@dataclass(frozen=True)
class Undone:
    task: Task  # the withdrawn answer's task, reserved again for the worker
    answer: dict[str, Any]  # what the withdrawn answer said: the page shows it again to correct, not to redo


def undo_last(worker: Worker | int, now: datetime | None = None, session: int | None = None) -> Undone:
    """Withdraw the latest answer of the worker's ``session`` while it is not aggregated; its task is reserved again.

    Never another session's answer, even of the same worker: a participant id in a URL is no
    secret, so the session is what proves the answer is the caller's.
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    last = db.session.scalar(
        select(Answer)
        .where(Answer.worker_id == worker_id, Answer.session_id.is_not_distinct_from(session))
        .order_by(Answer.submitted_at.desc(), Answer.id.desc())
        .limit(1)
    )
    if last is None:
        raise TaskError("There is no answer to undo", 409)
    aggregated = db.session.scalar(
        select(func.count())
        .select_from(Aggregate)
        .where(Aggregate.batch_id == last.item.batch_id, Aggregate.card_id == last.item.card_id)
    )
    if aggregated:
        raise TaskError("That answer was already counted in the results and cannot be undone", 409)
    item_id, answer = last.item_id, dict(last.payload or {})
    db.session.delete(last)
    reservation = store_reservation(item_id, worker_id, session, now + reservation_ttl())
    task = task_of(reservation)
    recount_items([item_id])
    db.session.commit()
    return Undone(task, answer)
