"""Fetching a task: open tasks, fetch-next with its top-up and holds, renewing, releasing lapsed holds.

Every function here runs inside the caller's app context and commits its own transaction.
Errors a worker can cause are :class:`annotation.task_errors.TaskError`.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from core.db import db, one_writer, read_only, utcnow

from . import assignment as strategy
from .crowd_settings import reservation_ttl
from .models import TASK_KINDS, Reservation, Worker
from .queries import (
    ANY_UNFINISHED,
    HAS_WALKABLE,
    INSERT_RESERVATION,
    LAPSED_ITEMS,
    LOCK_FREE_ITEMS,
    LOCK_ITEMS,
    OPEN_BATCHES,
    OPEN_GOLD,
    OPEN_ITEMS,
    OPEN_ITEMS_LOCKED,
    OPEN_TASKS,
    RELEASE_LAPSED,
    RENEW_RESERVATION,
    SERVED,
    UNFINISHED,
    WORKER_FLAGGED,
    as_utc,
    on_sqlite,
    recount_items,
    run_prebuilt,
    worker_id_of,
)
from .task_errors import TaskError

# Why fetching is built this way (measured with `keystone bench crowd`, 50 annotators under waitress
# on SQLite, and at 25,000 items): SQLite runs one write transaction at a time and the server
# runs Python on one core, so the write-lock hold time and the Python spent per request both
# turn into queueing for fifty annotators; and a collection of 250,000 cards makes batches of
# tens of thousands of items, so nothing on the hot path may load a whole batch.
# - Every item carries slot counters, ``answers`` (usable) and ``taken`` (usable answers + open
#   reservations), and a fixed ``rank`` in the batch's shuffle. Every write that changes an
#   item's answers or reservations recounts that item from its rows in the same transaction
#   (:data:`annotation.queries.RECOUNT`), so the counters never drift from the rows they cache.
# - Fetch-next is one short write transaction: read the worker's open tasks and, when it needs
#   more, release the holds that lapsed (an index seek when none did), walk
#   ``ix_crowd_batch_items_open`` (most taken first, then rank, as the pure strategy orders
#   them) to the first items this worker may take, insert their reservations and recount them.
#   None of it grows with the batch.
# - PostgreSQL: the walk locks the items it takes FOR NO KEY UPDATE SKIP LOCKED, so concurrent
#   fetches take different items instead of queueing on one, and re-checks ``taken < N`` on the
#   locked row; every statement after a lock sees what was committed before it (READ
#   COMMITTED), so recounts are exact. Waiting locks are taken in id order (no deadlocks).
#   SQLite's BEGIN IMMEDIATE serializes writers, and the writers of every server process queue
#   for it at :func:`core.db.one_writer` rather than in SQLite's sleeping busy handler.
# - Hot statements are built once with bound parameters and run on the session's connection:
#   building a select() costs about as much Python as running it, ORM row handling more.


@dataclass(frozen=True)
class Task:
    reservation_token: str
    batch_id: int
    kind: str
    card_id: int
    card_size: tuple[int, int]  # (width, height) of the original, the frame of crop boxes
    expires_at: datetime

    def as_json(self) -> dict[str, Any]:
        return {
            "token": self.reservation_token,
            "batch": self.batch_id,
            "kind": self.kind,
            "card_width": self.card_size[0],
            "card_height": self.card_size[1],
            "expires_at": self.expires_at.isoformat(),
        }


def task_of(reservation: Reservation) -> Task:
    item, card = reservation.item, reservation.item.card
    return Task(
        reservation.token, item.batch_id, item.batch.kind, card.id, (card.width, card.height), as_utc(reservation.expires_at)
    )


def release_lapsed_holds(now: datetime) -> int:
    """Put the slots of reservations that lapsed by ``now`` back in the pool; how many items changed.

    The reservation rows stay (``released_at`` set), so a late submit gets an exact reason and
    the same worker renews rather than duplicates them. PostgreSQL: items another transaction
    holds are skipped; that transaction recounts them itself, and the next fetch sweeps again.
    """
    ids = sorted(set(run_prebuilt(LAPSED_ITEMS, {"now": now}).scalars()))
    if not ids:
        return 0
    if not on_sqlite():
        ids = list(run_prebuilt(LOCK_FREE_ITEMS, {"item_ids": ids}).scalars())
        if not ids:
            return 0
    run_prebuilt(RELEASE_LAPSED, {"item_ids": ids, "now": now})
    recount_items(ids, locked=True)
    return len(ids)


def open_tasks(worker: Worker | int, kind: str, now: datetime, session: int | None = None) -> list[Task]:
    """The open (unanswered, unexpired) tasks of ``kind`` the worker holds in ``session``, oldest first.

    ``session`` is a :class:`CrowdSession` id; None means the tasks held outside any session
    (in-process callers: the simulator, tests), never another session's.
    """
    rows = run_prebuilt(OPEN_TASKS, {"worker_id": worker_id_of(worker), "session_id": session, "kind": kind, "now": now})
    return [Task(r.token, r.batch_id, r.kind, r.card_id, (r.width, r.height), as_utc(r.expires_at)) for r in rows]


def _hold(row: Any, worker_id: int, session: int | None, batch_id: int, kind: str, now: datetime, expires_at: datetime) -> Task:
    """Reserve the item of a walk row for the worker's session: renew their lapsed reservation or insert one.

    A lapsed reservation of another session of the same worker gets a new token: the old
    session still knows the old one, and a token is all the image and submit routes ask for.
    """
    if row.mine is not None:
        token = row.mine_token if row.mine_session == session else secrets.token_urlsafe(24)
        run_prebuilt(
            RENEW_RESERVATION,
            {"reservation_id": row.mine, "expires": expires_at, "created": now, "holder": session, "new_token": token},
        )
    else:
        token = secrets.token_urlsafe(24)
        run_prebuilt(
            INSERT_RESERVATION,
            {
                "item_id": row.id,
                "worker_id": worker_id,
                "session_id": session,
                "token": token,
                "created_at": now,
                "expires_at": expires_at,
            },
        )
    return Task(token, batch_id, kind, row.card_id, (row.width, row.height), as_utc(expires_at))


def _reserve_in_batch(
    batch: Any, worker_id: int, session: int | None, kind: str, wanted: int, now: datetime
) -> tuple[list[Task], strategy.NoTask | None]:
    """Inside the write transaction: up to ``wanted`` tasks of one batch for the worker, and why no more.

    The same rules as :func:`annotation.assignment.next_assignment` (a test holds the two to
    the same choices), answered from the index instead of the whole batch.
    """
    batch_id, n, gold_rate = batch
    params = {"batch_id": batch_id, "worker_id": worker_id, "n": n, "limit": wanted}
    regular = list(run_prebuilt(OPEN_ITEMS if on_sqlite() else OPEN_ITEMS_LOCKED, params))
    if not regular:
        return [], _why_nothing(batch_id, n, worker_id)
    policy = strategy.AssignmentPolicy(answers_per_item=n, gold_rate=gold_rate, reservation_ttl=reservation_ttl(), seed=batch_id)
    expires_at = now + policy.reservation_ttl
    served = run_prebuilt(SERVED, params).scalar() if gold_rate > 0 else 0
    gold: dict[int, Any] | None = None  # read on the first gold draw only (one draw in ten by default)
    taken: list[Any] = []
    while regular and len(taken) < wanted:
        if gold_rate > 0 and strategy.gold_draw(worker_id, served, policy):
            if gold is None:
                gold = {row.id: row for row in run_prebuilt(OPEN_GOLD, params)}
            if gold:  # none left unseen by this worker: regular work, as the pure strategy does
                pick = strategy.least_seen_gold({item_id: row.answers for item_id, row in gold.items()}, worker_id, policy)
                taken.append(gold.pop(int(pick)))
                served += 1
                continue
        taken.append(regular.pop(0))
        served += 1
    tasks = [_hold(row, worker_id, session, batch_id, kind, now, expires_at) for row in taken]
    recount_items([row.id for row in taken], locked=True)
    return tasks, None


def _why_nothing(batch_id: int, n: int, worker_id: int) -> strategy.NoTask:
    """Why the walk found no regular item of the batch for this worker (the pure strategy's reasons)."""
    params = {"batch_id": batch_id, "n": n, "worker_id": worker_id}
    if run_prebuilt(ANY_UNFINISHED, params).first() is None:
        return strategy.NoTask(strategy.NoTaskReason.BATCH_COMPLETE)
    count, retry_after = run_prebuilt(UNFINISHED, params).one()
    if count and retry_after is not None:
        return strategy.NoTask(strategy.NoTaskReason.ALL_RESERVED, retry_after=as_utc(retry_after))
    return strategy.NoTask(strategy.NoTaskReason.NOTHING_LEFT_FOR_WORKER)


def next_tasks(
    worker: Worker | int, kind: str = "judge", hold: int = 2, now: datetime | None = None, session: int | None = None
) -> tuple[list[Task], strategy.NoTask | None]:
    """The open tasks of the worker's ``session``, topping up to ``hold`` of them (the page preloads the second).

    The N-answers rule is the worker's, across sessions: no session gets an item the worker
    answered or holds in another one. What a session holds is its own (see :func:`open_tasks`).

    One short write transaction (see the section comment), so two workers asking at once never
    push an item beyond N and a worker never holds or answers one item twice. Returns the tasks
    oldest first and, when fewer than ``hold``, why there are no more (the first batch with
    work wins; otherwise the last batch's reason that is not "complete").
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    try:
        with one_writer():
            tasks, why = _top_up(worker_id, session, kind, hold, now)
            db.session.commit()
    except IntegrityError:
        # The same worker fetching in two tabs at once on PostgreSQL: one of them reserved the
        # item first. Whatever that fetch reserved is this worker's open tasks now.
        db.session.rollback()
        with read_only():
            return open_tasks(worker_id, kind, now, session)[:hold], None
    return tasks, why


def _top_up(
    worker_id: int, session: int | None, kind: str, hold: int, now: datetime
) -> tuple[list[Task], strategy.NoTask | None]:
    """:func:`next_tasks` inside its write transaction.

    Why one transaction and not a read first: in the steady state the worker holds one task
    (the preloaded one) and asks for one more, so a read transaction before the write was
    almost always followed by the write anyway, and a transaction costs as much Python as
    three statements.
    """
    held = open_tasks(worker_id, kind, now, session)
    if len(held) >= hold:
        return held, None
    if run_prebuilt(WORKER_FLAGGED, {"worker_id": worker_id, "session_id": session}).scalar():
        return held, strategy.NoTask(strategy.NoTaskReason.WORKER_FLAGGED)
    batches = run_prebuilt(OPEN_BATCHES, {"kind": kind}).all()
    if not batches:
        return held, strategy.NoTask(strategy.NoTaskReason.BATCH_COMPLETE)
    release_lapsed_holds(now)
    tasks, why = list(held), None
    for batch in batches:
        added, reason = _reserve_in_batch(batch, worker_id, session, kind, hold - len(tasks), now)
        tasks += added
        if len(tasks) >= hold:
            return tasks, None
        if reason is not None and (why is None or reason.reason != strategy.NoTaskReason.BATCH_COMPLETE):
            why = reason
    return tasks, why or strategy.NoTask(strategy.NoTaskReason.BATCH_COMPLETE)


def store_reservation(item_id: int, worker_id: int, session: int | None, expires_at: datetime) -> Reservation:
    # A lapsed reservation of the same worker on the same item is renewed, not duplicated.
    row = db.session.scalar(select(Reservation).where(Reservation.item_id == item_id, Reservation.worker_id == worker_id))
    if row is None:
        row = Reservation(
            item_id=item_id, worker_id=worker_id, session_id=session, token=secrets.token_urlsafe(24), expires_at=expires_at
        )
        db.session.add(row)
    else:
        if row.session_id != session:
            row.token = secrets.token_urlsafe(24)  # as in _hold: the other session knew the old token
        row.expires_at, row.answered_at, row.released_at, row.created_at = expires_at, None, None, utcnow()
        row.session_id = session
    db.session.flush()
    return row


def reservation_by_token(token: str) -> Reservation | None:
    return db.session.scalar(select(Reservation).where(Reservation.token == token))


def renew_reservation(worker: Worker | int, token: Any, now: datetime | None = None, session: int | None = None) -> Task:
    """Extend the worker's reservation ``token`` (open or lapsed) by the reservation time, if it still can be held.

    It can while it is unanswered and the item has a free slot or this reservation still
    counts in it. The page calls this when a reservation is about to lapse or lapsed while the
    annotator worked, so their drawn boxes are not lost. TaskError 404 / 403 / 409 otherwise.
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    if not isinstance(token, str) or not token:
        raise TaskError("Expected the task token to renew")
    with one_writer():
        row = db.session.scalar(select(Reservation).where(Reservation.token == token))
        if row is None:
            raise TaskError("No such task; fetch a new one", 404)
        if row.worker_id != worker_id or row.session_id != session:
            raise TaskError("This task is reserved for another worker", 403)
        if row.answered_at is not None:
            raise TaskError("You already answered this task", 409)
        item = row.item
        if not on_sqlite():
            run_prebuilt(LOCK_ITEMS, {"item_ids": [item.id]})
        db.session.refresh(item)
        counted = row.released_at is None
        if not counted and not item.is_gold and item.taken >= item.batch.answers_per_item:
            db.session.rollback()
            raise TaskError("Someone else took this card while your reservation had lapsed; fetch a new one", 409)
        row.expires_at, row.released_at = now + reservation_ttl(), None
        db.session.flush()
        recount_items([item.id], locked=True)
        task = task_of(row)
        db.session.commit()
    return task


def open_kinds(worker: Worker | int, session: int | None = None, now: datetime | None = None) -> list[str]:
    """The task kinds, in :data:`TASK_KINDS` order, with work for this worker's session now: tasks it
    holds, or a free regular item of an open batch it has not answered or held. A read: nothing
    is reserved (a hold that lapsed but was not yet released by a fetch still counts as taken).
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    if run_prebuilt(WORKER_FLAGGED, {"worker_id": worker_id, "session_id": session}).scalar():
        return []
    kinds = []
    for kind in TASK_KINDS:
        if open_tasks(worker_id, kind, now, session):
            kinds.append(kind)
            continue
        for batch_id, n, _rate in run_prebuilt(OPEN_BATCHES, {"kind": kind}).all():
            if run_prebuilt(HAS_WALKABLE, {"batch_id": batch_id, "n": n, "worker_id": worker_id}).first() is not None:
                kinds.append(kind)
                break
    return kinds


def any_unfinished_batch() -> bool:
    """Whether any batch of any kind still wants answers (someone may hand theirs back)."""
    return any(run_prebuilt(OPEN_BATCHES, {"kind": kind}).first() is not None for kind in TASK_KINDS)
