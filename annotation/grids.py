"""Confirm grids: fetching a grid of confirm tasks (gold hidden in it) and submitting its taps.

A grid is nothing new in the database: each of its cards is an ordinary reservation of a
confirm batch item, answered by an ordinary answer, so slot counters, N answers per card,
lapsed holds, undo, gold scoring and flagging all work as for judge and crop tasks. What a
grid adds: it reserves many items at once, always with a few gold items among them (a grid
with no gold would let a careless worker through unseen), and submits all its answers in one
post with one idempotency key.

Every function here runs inside the caller's app context and commits its own transactions.
Errors a worker can cause are :class:`annotation.task_errors.TaskError`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy.exc import IntegrityError

from core.db import db, one_writer, read_only, utcnow
from core.models import Card

from . import assignment as strategy
from .answers import CardSize, submit, validate_payload
from .confirm import grid_order, pick_gold
from .crowd_settings import MAX_GRID, grid_size, reservation_ttl
from .models import BatchItem
from .queries import (
    OPEN_BATCHES,
    OPEN_GOLD,
    OPEN_ITEMS,
    OPEN_ITEMS_LOCKED,
    WORKER_FLAGGED,
    on_sqlite,
    recount_items,
    run_prebuilt,
    worker_id_of,
)
from .reservations import Task, _hold, _why_nothing, open_tasks, release_lapsed_holds
from .task_errors import TaskError

# The gold a grid may hide, with its answers so far and its known taps (to mix right and wrong).
GRID_GOLD = OPEN_GOLD.add_columns(BatchItem.__table__.c.gold_answer)


def next_grid(worker: Any, now: datetime | None = None, session: int | None = None) -> tuple[list[Task], strategy.NoTask | None]:
    """The worker's grid: the confirm tasks their session holds (a reload shows the same grid),
    else a new one of up to :func:`grid_size` cards from the oldest confirm batch with work,
    the batch's least-answered gold items this worker has not seen mixed in; in grid order
    (:func:`annotation.confirm.grid_order`). One write transaction, as
    :func:`annotation.reservations.next_tasks`.
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    size, gold_wanted = grid_size()
    try:
        with one_writer():
            tasks, why = _reserve_grid(worker_id, session, size, gold_wanted, now)
            db.session.commit()
    except IntegrityError:
        # Two tabs of one worker fetching at once on PostgreSQL: the other one's grid is theirs.
        db.session.rollback()
        with read_only():
            tasks, why = open_tasks(worker_id, "confirm", now, session), None
    return [tasks[i] for i in grid_order((i, t.reservation_token) for i, t in enumerate(tasks))], why


def _reserve_grid(
    worker_id: int, session: int | None, size: int, gold_wanted: int, now: datetime
) -> tuple[list[Task], strategy.NoTask | None]:
    held = open_tasks(worker_id, "confirm", now, session)
    if held:
        return held, None
    if run_prebuilt(WORKER_FLAGGED, {"worker_id": worker_id, "session_id": session}).scalar():
        return [], strategy.NoTask(strategy.NoTaskReason.WORKER_FLAGGED)
    batches = run_prebuilt(OPEN_BATCHES, {"kind": "confirm"}).all()
    release_lapsed_holds(now)
    why: strategy.NoTask | None = None
    for batch_id, n, _rate in batches:
        params = {"batch_id": batch_id, "worker_id": worker_id, "n": n, "limit": size - gold_wanted}
        regular = list(run_prebuilt(OPEN_ITEMS if on_sqlite() else OPEN_ITEMS_LOCKED, params))
        if not regular:
            reason = _why_nothing(batch_id, n, worker_id)
            if why is None or reason.reason != strategy.NoTaskReason.BATCH_COMPLETE:
                why = reason
            continue
        candidates = {row.id: row for row in run_prebuilt(GRID_GOLD, params)}
        chosen = pick_gold([(row.id, row.answers, row.gold_answer or {}) for row in candidates.values()], gold_wanted)
        gold = [candidates[item_id] for item_id in chosen]
        expires_at = now + reservation_ttl()
        tasks = [_hold(row, worker_id, session, batch_id, "confirm", now, expires_at) for row in [*regular, *gold]]
        recount_items([row.id for row in [*regular, *gold]], locked=True)
        return tasks, None
    return [], why or strategy.NoTask(strategy.NoTaskReason.BATCH_COMPLETE)


@dataclass
class GridSubmitted:
    stored: int = 0
    duplicates: int = 0
    refused: list[dict[str, Any]] = field(default_factory=list)  # {"token", "message", "status"}

    def as_json(self) -> dict[str, Any]:
        return {"stored": self.stored, "duplicates": self.duplicates, "refused": self.refused}


def _checked_grid(answers: Any, key: Any) -> list[tuple[str, dict[str, bool]]]:
    """(token, taps) per card, or TaskError before anything is stored: a bad post stores nothing."""
    if not isinstance(key, str) or not 8 <= len(key) <= 40:
        raise TaskError("Expected an idempotency key of 8 to 40 characters")
    if not isinstance(answers, list) or not 1 <= len(answers) <= MAX_GRID:
        raise TaskError(f"Expected the grid's answers as a list of 1 to {MAX_GRID} cards")
    checked: list[tuple[str, dict[str, bool]]] = []
    for position, entry in enumerate(answers, 1):
        if not isinstance(entry, dict) or not isinstance(entry.get("token"), str) or not entry["token"]:
            raise TaskError(f'Expected card {position} of the grid as {{"token": ..., "taps": {{...}}}}')
        try:
            taps = validate_payload("confirm", entry.get("taps"), CardSize(1, 1))
        except TaskError as exc:
            raise TaskError(f"Card {position} of the grid: {exc.message}") from None
        checked.append((entry["token"], taps))
    if len({token for token, _ in checked}) != len(checked):
        raise TaskError("Expected each card of the grid once")
    return checked


def submit_grid(worker: Any, answers: Any, key: Any, session: int | None = None, now: datetime | None = None) -> GridSubmitted:
    """Store the taps of a grid: ``answers`` is ``[{"token": reservation token, "taps":
    {"upside_down", "inverted", "swapped"}}]`` (an untapped card is all false: confirmed).

    Each card is one :func:`annotation.answers.submit` under the key ``<key>.<token>``, so a
    repeated post (a double click, a retry after a lost reply) stores nothing twice and says
    which were duplicates. A card refused (its hold lapsed and someone took it, the worker was
    just flagged on gold) does not stop the others; if every card is refused, the first
    refusal is raised (a 4xx).
    """
    checked = _checked_grid(answers, key)
    outcome = GridSubmitted()
    first: TaskError | None = None
    for token, taps in checked:
        try:
            result = submit(worker, token, taps, f"{key}.{token}", now=now, session=session)
        except TaskError as exc:
            db.session.rollback()
            first = first or exc
            outcome.refused.append({"token": token, "message": exc.message, "status": exc.status})
            continue
        if result.duplicate:
            outcome.duplicates += 1
        else:
            outcome.stored += 1
    if first is not None and not outcome.stored and not outcome.duplicates:
        raise first
    return outcome


def card_photo_boxes(card: Card) -> tuple[list[float], list[float]]:
    """The card's two photos in scan pixels: the orientation step's photo areas, else the
    filter's split, else the two halves (what rectification would cut, in that order)."""
    from pipeline.stages.filter import filter_boxes
    from pipeline.stages.orientation import photo_area_boxes

    boxes = photo_area_boxes(card) or filter_boxes(card)
    if boxes.get("left_box") and boxes.get("right_box"):
        return list(boxes["left_box"]), list(boxes["right_box"])
    half = card.width // 2
    return [0, 0, half, card.height], [card.width - half, 0, card.width, card.height]
