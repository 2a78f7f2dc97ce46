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
from typing import Any, NamedTuple

import numpy as np
from flask import current_app
from sqlalchemy import (
    Integer,
    and_,
    bindparam,
    case,
    delete,
    func,
    inspect as sa_inspect,
    or_,
    select,
    update,
)
from sqlalchemy.exc import IntegrityError

from app.db import db, one_writer, read_only, utcnow
from app.models import Card

from . import assignment as strategy
from .aggregation import (
    ALL_QUESTIONS,
    OPTIONAL_QUESTIONS,
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
from .models import (
    TASK_KINDS,
    Aggregate,
    Answer,
    Batch,
    BatchItem,
    CrowdSession,
    Reservation,
    Worker,
)

DEFAULT_RESERVATION_MINUTES = 10
DEFAULT_MIN_BOX_PX = 16
DEFAULT_GOLD_THRESHOLD = 0.7
DEFAULT_MIN_GOLD = 3
HALVES: tuple[str, ...] = ("left", "right")


class TaskError(Exception):
    """Something the worker (or an admin) did wrong: shown to them, status for the HTTP reply."""

    def __init__(self, message: str, status: int = 400, retry_after: int | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.status = status
        self.retry_after = retry_after  # seconds, sent as Retry-After (429 answers)


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
    db.session.flush()  # ids: the shuffle is keyed on them
    for item in batch.items:
        item.rank = strategy.item_rank(batch.id, item.id)
    db.session.commit()
    return batch


def review_queue_card_ids() -> list[int]:
    """Cards the filter sent to human judgement (state ``review``)."""
    return list(db.session.scalars(select(Card.id).where(Card.state == "review").order_by(Card.id)))


def orientation_queue_card_ids() -> list[int]:
    """Cards whose orientation the orientation step could not decide (it asked, or failed) and
    that no crowd judgement or curator has decided yet, whatever their filter band: they wait
    for a judge batch (``keystone crowd create-batch --from-review`` includes them)."""
    from app.runs import waiting_for_people

    waiting = waiting_for_people()["orientation"]
    # A card already in a judge batch whose answers are not aggregated yet is on its way.
    in_flight: set[int] = set()
    for start in range(0, len(waiting), 500):
        chunk = waiting[start:start + 500]
        in_flight.update(db.session.scalars(
            select(BatchItem.card_id).join(Batch, Batch.id == BatchItem.batch_id)
            .where(Batch.kind == "judge", BatchItem.card_id.in_(chunk), ~BatchItem.is_gold,
                   ~select(Aggregate.id).where(Aggregate.batch_id == BatchItem.batch_id,
                                               Aggregate.card_id == BatchItem.card_id).exists())))
    return [card_id for card_id in waiting if card_id not in in_flight]


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
#
# Why it is built this way (measured with `keystone bench crowd`, 50 annotators under waitress
# on SQLite, and at 25,000 items): SQLite runs one write transaction at a time and the server
# runs Python on one core, so the write-lock hold time and the Python spent per request both
# turn into queueing for fifty annotators; and a collection of 250,000 cards makes batches of
# tens of thousands of items, so nothing on the hot path may load a whole batch.
# - Every item carries slot counters, ``answers`` (usable) and ``taken`` (usable answers + open
#   reservations), and a fixed ``rank`` in the batch's shuffle. Every write that changes an
#   item's answers or reservations recounts that item from its rows in the same transaction
#   (:data:`_RECOUNT`), so the counters never drift from the rows they cache.
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
#   for it at :func:`app.db.one_writer` rather than in SQLite's sleeping busy handler.
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
        return {"token": self.reservation_token, "batch": self.batch_id, "kind": self.kind,
                "card_width": self.card_size[0], "card_height": self.card_size[1],
                "expires_at": self.expires_at.isoformat()}


class CardSize(NamedTuple):
    """What answer validation needs of a card: the original's size in pixels (a Card also fits)."""

    width: int
    height: int


def worker_id_of(worker: Worker | int) -> int:
    """The worker's id without a query, even when the row is expired after a rolled-back read."""
    if isinstance(worker, int):
        return worker
    identity = sa_inspect(worker).identity
    return int(identity[0]) if identity else int(worker.id)


def _task(reservation: Reservation) -> Task:
    item, card = reservation.item, reservation.item.card
    return Task(reservation.token, item.batch_id, item.batch.kind, card.id, (card.width, card.height),
                _aware(reservation.expires_at))


_items, _reservations, _answers = BatchItem.__table__, Reservation.__table__, Answer.__table__


def _held(reservations: Any) -> Any:
    """A reservation counts toward its item's ``taken`` while neither answered nor released."""
    return and_(reservations.c.answered_at.is_(None), reservations.c.released_at.is_(None))


_HELD = _held(_reservations)


def _held_by(worker: Any, item: Any = _items.c.id) -> Any:
    """EXISTS: ``worker`` answered ``item`` or holds it (a released reservation does not count)."""
    # Aliases: the enclosing query may join the answers or reservations tables itself.
    answers, reservations = _answers.alias("worker_answers"), _reservations.alias("worker_holds")
    return or_(
        select(answers.c.id).where(answers.c.item_id == item, answers.c.worker_id == worker).exists(),
        select(reservations.c.id).where(reservations.c.item_id == item, reservations.c.worker_id == worker,
                                        _held(reservations)).exists())


def _recount_statement() -> Any:
    usable = (select(func.count()).select_from(_answers)
              .where(_answers.c.item_id == _items.c.id, _answers.c.flagged.is_(False)).scalar_subquery())
    held = (select(func.count()).select_from(_reservations)
            .where(_reservations.c.item_id == _items.c.id, _HELD).scalar_subquery())
    return (_items.update().where(_items.c.id.in_(bindparam("item_ids", expanding=True)))
            .values(answers=usable, taken=usable + held))


_RECOUNT = _recount_statement()
# FOR NO KEY UPDATE: it serializes writers of one item, but not the KEY SHARE locks that
# inserting an answer or a reservation (foreign keys to the item) takes.
_LOCK_ITEMS = (select(_items.c.id).where(_items.c.id.in_(bindparam("item_ids", expanding=True)))
               .order_by(_items.c.id).with_for_update(key_share=True))
_LOCK_FREE_ITEMS = (select(_items.c.id).where(_items.c.id.in_(bindparam("item_ids", expanding=True)))
                    .order_by(_items.c.id).with_for_update(key_share=True, skip_locked=True))
SWEEP_LIMIT = 500  # lapsed holds released per fetch; the next fetch releases the rest
_LAPSED_ITEMS = (select(_reservations.c.item_id)
                 .where(_HELD, _reservations.c.expires_at <= bindparam("now")).limit(SWEEP_LIMIT))
_RELEASE_LAPSED = (_reservations.update()
                   .where(_reservations.c.item_id.in_(bindparam("item_ids", expanding=True)), _HELD,
                          _reservations.c.expires_at <= bindparam("now"))
                   .values(released_at=bindparam("now")))

_OPEN_TASKS = (
    select(Reservation.token, BatchItem.batch_id, Batch.kind, BatchItem.card_id, Card.width, Card.height,
           Reservation.expires_at)
    .join(BatchItem, Reservation.item_id == BatchItem.id).join(Batch, BatchItem.batch_id == Batch.id)
    .join(Card, BatchItem.card_id == Card.id)
    .where(Reservation.worker_id == bindparam("worker_id"),
           Reservation.session_id.is_not_distinct_from(bindparam("session_id", type_=Integer)),
           Reservation.answered_at.is_(None), Reservation.released_at.is_(None), Batch.kind == bindparam("kind"),
           Reservation.expires_at > bindparam("now"))
    .order_by(Reservation.created_at, Reservation.id))
# Refused work: the worker is flagged on gold (in any session), or this session inherited a flag
# (annotation.sessions: a flagged worker of the same study came from the same address).
_WORKER_FLAGGED = select(or_(Worker.flagged, select(CrowdSession.id).where(
    CrowdSession.id == bindparam("session_id", type_=Integer), CrowdSession.flagged.is_(True)).exists())
).where(Worker.id == bindparam("worker_id"))
# A session's progress: only its own answers (another session of the worker is not shown).
_ANSWER_COUNT = select(func.count()).select_from(Answer).where(
    Answer.worker_id == bindparam("worker_id"),
    Answer.session_id.is_not_distinct_from(bindparam("session_id", type_=Integer)))
# Batches with a regular item below N usable answers: one index seek per batch.
_OPEN_BATCHES = (
    select(Batch.id, Batch.answers_per_item, Batch.gold_rate)
    .where(Batch.kind == bindparam("kind"),
           select(_items.c.id).where(_items.c.batch_id == Batch.id, _items.c.is_gold.is_(False),
                                     _items.c.answers < Batch.answers_per_item).exists())
    .order_by(Batch.id))
# The walk: open regular items this worker may take, in the pure strategy's order, on the
# index (batch_id, is_gold, taken, rank) read backwards. ``mine`` is this worker's released
# (lapsed) reservation of the item, renewed rather than duplicated.
_mine = _reservations.alias("mine")
_OPEN_ITEMS = (
    select(_items.c.id, _items.c.card_id, Card.width, Card.height, _mine.c.id.label("mine"),
           _mine.c.token.label("mine_token"), _mine.c.session_id.label("mine_session"))
    .join(Card, _items.c.card_id == Card.id)
    .outerjoin(_mine, and_(_mine.c.item_id == _items.c.id, _mine.c.worker_id == bindparam("worker_id")))
    .where(_items.c.batch_id == bindparam("batch_id"), _items.c.is_gold.is_(False),
           _items.c.taken < bindparam("n"), ~_held_by(bindparam("worker_id")))
    .order_by(_items.c.taken.desc(), _items.c.rank.desc())
    .limit(bindparam("limit", type_=Integer)))
_OPEN_ITEMS_LOCKED = _OPEN_ITEMS.with_for_update(key_share=True, skip_locked=True, of=_items)
# Gold is never capped at N: every gold item this worker has not seen, with how often it was answered.
_OPEN_GOLD = (
    select(_items.c.id, _items.c.card_id, _items.c.answers, Card.width, Card.height, _mine.c.id.label("mine"),
           _mine.c.token.label("mine_token"), _mine.c.session_id.label("mine_session"))
    .join(Card, _items.c.card_id == Card.id)
    .outerjoin(_mine, and_(_mine.c.item_id == _items.c.id, _mine.c.worker_id == bindparam("worker_id")))
    .where(_items.c.batch_id == bindparam("batch_id"), _items.c.is_gold.is_(True), ~_held_by(bindparam("worker_id"))))
# How many items of the batch this worker answered or holds: the key of the gold draw. Driven
# from the worker's own rows (their indexes) with the item's batch looked up per row: a join
# lets SQLite's planner start from the batch's items instead. The two sets are disjoint, since
# an answer closes its reservation and an undo deletes the answer before renewing it.
def _batch_of(item: Any) -> Any:
    return select(_items.c.batch_id).where(_items.c.id == item).scalar_subquery()


_SERVED = select(
    select(func.count()).select_from(_answers)
    .where(_answers.c.worker_id == bindparam("worker_id"), _batch_of(_answers.c.item_id) == bindparam("batch_id"))
    .scalar_subquery()
    + select(func.count()).select_from(_reservations)
    .where(_reservations.c.worker_id == bindparam("worker_id"), _HELD,
           _batch_of(_reservations.c.item_id) == bindparam("batch_id"))
    .scalar_subquery())
# Why a batch has nothing for this worker: its unfinished regular items this worker has not
# touched, and the earliest lapse of a hold on them (they are all held by others, else the
# walk would have found one).
_UNFINISHED = (select(func.count(_items.c.id.distinct()), func.min(_reservations.c.expires_at))
               .select_from(_items)
               .outerjoin(_reservations, and_(_reservations.c.item_id == _items.c.id, _HELD))
               .where(_items.c.batch_id == bindparam("batch_id"), _items.c.is_gold.is_(False),
                      _items.c.answers < bindparam("n"), ~_held_by(bindparam("worker_id"))))
_ANY_UNFINISHED = select(_items.c.id).where(_items.c.batch_id == bindparam("batch_id"), _items.c.is_gold.is_(False),
                                            _items.c.answers < bindparam("n")).limit(1)
_INSERT_RESERVATION = _reservations.insert()
_RENEW_RESERVATION = (_reservations.update().where(_reservations.c.id == bindparam("reservation_id"))
                      .values(expires_at=bindparam("expires"), answered_at=None, released_at=None,
                              created_at=bindparam("created"), session_id=bindparam("holder"),
                              token=bindparam("new_token")))


def _on_sqlite() -> bool:
    return db.session.get_bind().dialect.name == "sqlite"


def _core(statement: Any, params: Mapping[str, Any]) -> Any:
    """Run a prebuilt statement on the session's connection: plain rows, none of the ORM's row handling.

    Same transaction as the session (a read-only one inside :func:`read_only`).
    """
    return db.session.connection().execute(statement, params)


def recount_items(item_ids: Iterable[int], *, locked: bool = False) -> None:
    """Recount ``answers`` and ``taken`` of these items from their rows, in the caller's write transaction.

    Every change to an item's answers or reservations calls this before committing. On
    PostgreSQL the items are locked first, in id order, unless the caller holds them already
    (``locked``), so this statement sees every change committed to them before it.
    """
    ids = sorted(set(item_ids))
    if not ids:
        return
    if not locked and not _on_sqlite():
        _core(_LOCK_ITEMS, {"item_ids": ids})
    _core(_RECOUNT, {"item_ids": ids})


def release_lapsed_holds(now: datetime) -> int:
    """Put the slots of reservations that lapsed by ``now`` back in the pool; how many items changed.

    The reservation rows stay (``released_at`` set), so a late submit gets an exact reason and
    the same worker renews rather than duplicates them. PostgreSQL: items another transaction
    holds are skipped; that transaction recounts them itself, and the next fetch sweeps again.
    """
    ids = sorted(set(_core(_LAPSED_ITEMS, {"now": now}).scalars()))
    if not ids:
        return 0
    if not _on_sqlite():
        ids = list(_core(_LOCK_FREE_ITEMS, {"item_ids": ids}).scalars())
        if not ids:
            return 0
    _core(_RELEASE_LAPSED, {"item_ids": ids, "now": now})
    recount_items(ids, locked=True)
    return len(ids)


def open_tasks(worker: Worker | int, kind: str, now: datetime, session: int | None = None) -> list[Task]:
    """The open (unanswered, unexpired) tasks of ``kind`` the worker holds in ``session``, oldest first.

    ``session`` is a :class:`CrowdSession` id; None means the tasks held outside any session
    (in-process callers: the simulator, tests), never another session's.
    """
    rows = _core(_OPEN_TASKS, {"worker_id": worker_id_of(worker), "session_id": session, "kind": kind, "now": now})
    return [Task(r.token, r.batch_id, r.kind, r.card_id, (r.width, r.height), _aware(r.expires_at)) for r in rows]


def answer_count(worker: Worker | int, session: int | None = None) -> int:
    """How many answers the worker has stored in ``session`` (the progress its page shows)."""
    return _core(_ANSWER_COUNT, {"worker_id": worker_id_of(worker), "session_id": session}).scalar() or 0


def _reservation_ttl() -> timedelta:
    return timedelta(minutes=float(_config("KEYSTONE_CROWD_RESERVATION_MINUTES", DEFAULT_RESERVATION_MINUTES)))


def _hold(row: Any, worker_id: int, session: int | None, batch_id: int, kind: str, now: datetime,
          expires_at: datetime) -> Task:
    """Reserve the item of a walk row for the worker's session: renew their lapsed reservation or insert one.

    A lapsed reservation of another session of the same worker gets a new token: the old
    session still knows the old one, and a token is all the image and submit routes ask for.
    """
    if row.mine is not None:
        token = row.mine_token if row.mine_session == session else secrets.token_urlsafe(24)
        _core(_RENEW_RESERVATION, {"reservation_id": row.mine, "expires": expires_at, "created": now,
                                   "holder": session, "new_token": token})
    else:
        token = secrets.token_urlsafe(24)
        _core(_INSERT_RESERVATION, {"item_id": row.id, "worker_id": worker_id, "session_id": session, "token": token,
                                    "created_at": now, "expires_at": expires_at})
    return Task(token, batch_id, kind, row.card_id, (row.width, row.height), _aware(expires_at))


def _reserve_in_batch(batch: Any, worker_id: int, session: int | None, kind: str, wanted: int,
                      now: datetime) -> tuple[list[Task], strategy.NoTask | None]:
    """Inside the write transaction: up to ``wanted`` tasks of one batch for the worker, and why no more.

    The same rules as :func:`annotation.assignment.next_assignment` (a test holds the two to
    the same choices), answered from the index instead of the whole batch.
    """
    batch_id, n, gold_rate = batch
    params = {"batch_id": batch_id, "worker_id": worker_id, "n": n, "limit": wanted}
    regular = list(_core(_OPEN_ITEMS if _on_sqlite() else _OPEN_ITEMS_LOCKED, params))
    if not regular:
        return [], _why_nothing(batch_id, n, worker_id)
    policy = strategy.AssignmentPolicy(answers_per_item=n, gold_rate=gold_rate, reservation_ttl=_reservation_ttl(),
                                       seed=batch_id)
    expires_at = now + policy.reservation_ttl
    served = _core(_SERVED, params).scalar() if gold_rate > 0 else 0
    gold: dict[int, Any] | None = None  # read on the first gold draw only (one draw in ten by default)
    taken: list[Any] = []
    while regular and len(taken) < wanted:
        if gold_rate > 0 and strategy.gold_draw(worker_id, served, policy):
            if gold is None:
                gold = {row.id: row for row in _core(_OPEN_GOLD, params)}
            if gold:  # none left unseen by this worker: regular work, as the pure strategy does
                pick = strategy.least_seen_gold({item_id: row.answers for item_id, row in gold.items()},
                                                worker_id, policy)
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
    if _core(_ANY_UNFINISHED, params).first() is None:
        return strategy.NoTask(strategy.NoTaskReason.BATCH_COMPLETE)
    count, retry_after = _core(_UNFINISHED, params).one()
    if count and retry_after is not None:
        return strategy.NoTask(strategy.NoTaskReason.ALL_RESERVED, retry_after=_aware(retry_after))
    return strategy.NoTask(strategy.NoTaskReason.NOTHING_LEFT_FOR_WORKER)


def next_tasks(worker: Worker | int, kind: str = "judge", hold: int = 2, now: datetime | None = None,
               session: int | None = None) -> tuple[list[Task], strategy.NoTask | None]:
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


def _top_up(worker_id: int, session: int | None, kind: str, hold: int,
            now: datetime) -> tuple[list[Task], strategy.NoTask | None]:
    """:func:`next_tasks` inside its write transaction.

    Why one transaction and not a read first: in the steady state the worker holds one task
    (the preloaded one) and asks for one more, so a read transaction before the write was
    almost always followed by the write anyway, and a transaction costs as much Python as
    three statements.
    """
    held = open_tasks(worker_id, kind, now, session)
    if len(held) >= hold:
        return held, None
    if _core(_WORKER_FLAGGED, {"worker_id": worker_id, "session_id": session}).scalar():
        return held, strategy.NoTask(strategy.NoTaskReason.WORKER_FLAGGED)
    batches = _core(_OPEN_BATCHES, {"kind": kind}).all()
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


def _store_reservation(item_id: int, worker_id: int, session: int | None, expires_at: datetime) -> Reservation:
    # A lapsed reservation of the same worker on the same item is renewed, not duplicated.
    row = db.session.scalar(select(Reservation).where(Reservation.item_id == item_id,
                                                      Reservation.worker_id == worker_id))
    if row is None:
        row = Reservation(item_id=item_id, worker_id=worker_id, session_id=session, token=secrets.token_urlsafe(24),
                          expires_at=expires_at)
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


# ---------------------------------------------------------------------------------------------
# Answers


def _as_bool(payload: Mapping[str, Any], key: str) -> bool:
    value = payload.get(key)
    if not isinstance(value, bool):
        raise TaskError(f"Expected {key} to be true or false, got {value!r}")
    return value


def _as_box(value: Any, half: str, card: Card | CardSize) -> list[float]:
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


def validate_payload(kind: str, payload: Any, card: Card | CardSize) -> dict[str, Any]:
    """The canonical answer, or TaskError saying what is wrong with it.

    judge: ``{"is_stereo", "upside_down", "inverted"}`` booleans, and ``swapped`` (the photos in
    the wrong eye order) where the page asked it; stored only when given, so aggregation can tell
    "not asked" from "no". crop: ``{"left", "right"}`` boxes ``[x0, y0, x1, y1]`` in original
    image pixels, inside the card, at least the minimum size.
    """
    if not isinstance(payload, dict):
        raise TaskError(f"Expected a JSON object as the answer, got {type(payload).__name__}")
    expected = set(ALL_QUESTIONS) if kind == "judge" else set(HALVES)
    extra = sorted(set(payload) - expected)
    if extra:
        raise TaskError(f"Unexpected fields in the answer: {', '.join(extra)}")
    if kind == "judge":
        answer = {q: _as_bool(payload, q) for q in QUESTIONS}
        answer.update({q: _as_bool(payload, q) for q in OPTIONAL_QUESTIONS if q in payload})
        return answer
    return {half: _as_box(payload.get(half), half, card) for half in HALVES}


@dataclass(frozen=True)
class Submitted:
    answer_id: int
    duplicate: bool  # True when this post repeated an answer already stored


_ANSWER_BY_KEY = select(Answer.id, Answer.worker_id, Answer.session_id).where(Answer.idempotency_key == bindparam("key"))
_RESERVATION_TO_ANSWER = (
    select(Reservation.id, Reservation.worker_id, Reservation.session_id, Reservation.answered_at,
           Reservation.released_at,
           Reservation.expires_at, Reservation.item_id, BatchItem.is_gold, Batch.kind, Card.width, Card.height)
    .join(BatchItem, Reservation.item_id == BatchItem.id).join(Batch, BatchItem.batch_id == Batch.id)
    .join(Card, BatchItem.card_id == Card.id).where(Reservation.token == bindparam("token")))
_RESERVATION_STATE = (select(Reservation.id, Reservation.worker_id, Reservation.session_id, Reservation.answered_at,
                             Reservation.released_at, Reservation.expires_at)
                      .where(Reservation.id == bindparam("reservation_id")))
# Matches only while the reservation is this worker's session's, unanswered and still counted
# (not lapsed, not released by a sweep): the claim and the check in one.
_CLAIM_RESERVATION = (_reservations.update()
                      .where(_reservations.c.id == bindparam("reservation_id"),
                             _reservations.c.worker_id == bindparam("claimant"),
                             _reservations.c.session_id.is_not_distinct_from(bindparam("claimant_session", type_=Integer)),
                             _HELD,
                             _reservations.c.expires_at > bindparam("at"))
                      .values(answered_at=bindparam("at")))
_INSERT_ANSWER = _answers.insert()


def submit(worker: Worker | int, reservation_token: str, payload: Any, idempotency_key: str,
           now: datetime | None = None, session: int | None = None) -> Submitted:
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
        held = _core(_RESERVATION_TO_ANSWER, {"token": reservation_token}).first() \
            if isinstance(reservation_token, str) else None
        _check_reservation(held, worker_id, session, now)
        answer = validate_payload(held.kind, payload, CardSize(held.width, held.height))
        flagged = bool(_core(_WORKER_FLAGGED, {"worker_id": worker_id, "session_id": session}).scalar())
    try:
        with one_writer():
            if not _on_sqlite():
                _core(_LOCK_ITEMS, {"item_ids": [held.item_id]})
            claimed = _core(_CLAIM_RESERVATION, {"reservation_id": held.id, "claimant": worker_id,
                                                 "claimant_session": session, "at": now})
            if claimed.rowcount == 1:
                answer_id = _core(_INSERT_ANSWER, {
                    "item_id": held.item_id, "worker_id": worker_id, "session_id": session, "payload": answer,
                    "submitted_at": now,
                    "idempotency_key": idempotency_key, "flagged": flagged}).inserted_primary_key[0]
                recount_items([held.item_id], locked=True)
                db.session.commit()
            else:
                db.session.rollback()
    except IntegrityError:
        # A replay that raced past the checks: the unique key and (item, worker) keep one answer.
        db.session.rollback()
        with read_only():
            stored = db.session.scalar(select(Answer.id).where(Answer.item_id == held.item_id,
                                                               Answer.worker_id == worker_id))
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
            _check_reservation(_core(_RESERVATION_STATE, {"reservation_id": held.id}).first(),
                               worker_id, session, now)
        raise TaskError("This task changed while you answered; fetch a new one", 409)
    if held.is_gold:
        update_worker_quality([worker_id])
    return Submitted(int(answer_id), False)


def _answer_by_key(idempotency_key: str, worker_id: int, session: int | None) -> Submitted | None:
    earlier = _core(_ANSWER_BY_KEY, {"key": idempotency_key}).first()
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
    if _aware(held.expires_at) <= now or held.released_at is not None:
        raise TaskError(f"Your reservation of this task expired at {_aware(held.expires_at):%H:%M:%S} UTC; "
                        "fetch a new task", 409)


def undo_last(worker: Worker | int, now: datetime | None = None, session: int | None = None) -> Task:
    """Withdraw the latest answer of the worker's ``session`` while it is not aggregated; its task is reserved again.

    Never another session's answer, even of the same worker: a participant id in a URL is no
    secret, so the session is what proves the answer is the caller's.
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    last = db.session.scalar(select(Answer).where(Answer.worker_id == worker_id,
                                                  Answer.session_id.is_not_distinct_from(session))
                             .order_by(Answer.submitted_at.desc(), Answer.id.desc()).limit(1))
    if last is None:
        raise TaskError("There is no answer to undo", 409)
    aggregated = db.session.scalar(select(func.count()).select_from(Aggregate).where(
        Aggregate.batch_id == last.item.batch_id, Aggregate.card_id == last.item.card_id))
    if aggregated:
        raise TaskError("That answer was already counted in the results and cannot be undone", 409)
    item_id = last.item_id
    db.session.delete(last)
    reservation = _store_reservation(item_id, worker_id, session, now + _reservation_ttl())
    task = _task(reservation)
    recount_items([item_id])
    db.session.commit()
    return task


# ---------------------------------------------------------------------------------------------
# Quality and aggregation


def _gold_label(kind: str, answer: Mapping[str, Any], gold: Mapping[str, Any]) -> int:
    """1 when the answer matches gold: every judgement both have, or both boxes at IoU >= 0.5."""
    if kind == "judge":
        return int(all(bool(answer[q]) == bool(gold[q]) for q in ALL_QUESTIONS if q in answer and q in gold))
    return int(all(box_iou(answer[h], gold[h])[0, 0] >= 0.5 for h in HALVES))


def update_worker_quality(worker_ids: Iterable[int] | None = None) -> dict[int, dict[str, Any]]:
    """Gold accuracy per worker; those below the threshold are flagged with all their answers.

    Scores are read in a read transaction; the write lock is taken only when a worker must be
    newly flagged (every gold submit calls this, and almost all of them change nothing).
    """
    query = select(Answer.item_id, Answer.worker_id, Answer.payload, BatchItem.gold_answer, Batch.kind).join(
        BatchItem, Answer.item_id == BatchItem.id).join(Batch, BatchItem.batch_id == Batch.id).where(
        BatchItem.is_gold.is_(True))
    if worker_ids is not None:
        query = query.where(Answer.worker_id.in_(list(worker_ids)))
    threshold = float(_config("KEYSTONE_CROWD_GOLD_THRESHOLD", DEFAULT_GOLD_THRESHOLD))
    with read_only():
        labels = [LabelAnswer(item_id, worker_id, _gold_label(kind, payload, gold_answer or {}))
                  for item_id, worker_id, payload, gold_answer, kind in db.session.execute(query)]
        scores = gold_accuracy(labels, {a.item_id: 1 for a in labels})
        flagged = flag_workers(scores, threshold, int(_config("KEYSTONE_CROWD_MIN_GOLD", DEFAULT_MIN_GOLD)))
        newly = list(db.session.scalars(select(Worker.id).where(Worker.id.in_(list(flagged)),
                                                                 Worker.flagged.is_(False)))) if flagged else []
    if newly:
        no_sync = {"synchronize_session": False}  # the commit below expires whatever the session holds
        with one_writer():
            # Their answers stop filling slots and their open reservations go back to the pool
            # at once: every item they touched is recounted (locked first on PostgreSQL, so a
            # submit holding one of those items cannot wait on these rows while we wait on it).
            touched = sorted(set(db.session.scalars(select(Answer.item_id).where(Answer.worker_id.in_(newly))))
                             | set(db.session.scalars(select(Reservation.item_id).where(
                                 Reservation.worker_id.in_(newly), Reservation.answered_at.is_(None)))))
            if touched and not _on_sqlite():
                _core(_LOCK_ITEMS, {"item_ids": touched})
            db.session.execute(update(Worker).where(Worker.id.in_(newly)).values(flagged=True)
                               .execution_options(**no_sync))
            db.session.execute(update(Answer).where(Answer.worker_id.in_(newly)).values(flagged=True)
                               .execution_options(**no_sync))
            db.session.execute(delete(Reservation).where(Reservation.worker_id.in_(newly),
                                                         Reservation.answered_at.is_(None))
                               .execution_options(**no_sync))
            recount_items(touched, locked=True)
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
        asked = [q for q in ALL_QUESTIONS if q in QUESTIONS or any(q in a.payload for a in answers)]
        for q in asked:
            R = np.full((len(workers), len(item_ids)), np.nan)
            for a in answers:
                if a.item_id in column and q in a.payload:
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


def _judgement(payload: Mapping[str, Any]) -> Judgement:
    """A stored judge answer (or gold answer) as a :class:`Judgement`; a question not asked is None."""
    return Judgement(**{q: bool(payload[q]) for q in QUESTIONS},
                     **{q: bool(payload[q]) for q in OPTIONAL_QUESTIONS if q in payload})


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
        judged = [JudgementAnswer(a.item_id, a.worker_id, _judgement(a.payload)) for a in answers]
        gold = {it.id: _judgement(it.gold_answer) for it in items.values() if it.is_gold and it.gold_answer}
        ds = aggregate_judgements(judged, gold)
        for it in finished:
            # swapped: only where this card's answers asked it (older pages did not).
            here = [q for q in ALL_QUESTIONS if q in QUESTIONS or any(q in a.payload for a in by_item[it.id])]
            label = {q: bool(ds[q].label_of(it.id)) for q in here}
            posterior = {q: [round(float(p), 6) for p in ds[q].posterior(it.id)] for q in here}
            asked = here if label["is_stereo"] else ["is_stereo"]
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
        if row is not None and row.resolved_by is not None:
            # A curator's decision is the card's truth: re-aggregating never overwrites it.
            approved += 1
            continue
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
    """Done / reserved / expired counts for a batch and per worker, with each worker's gold score in it.

    Per worker: ``done`` answers, open ``reserved`` and lapsed ``expired`` reservations,
    ``gold_correct`` of ``gold_total`` gold answers (see :func:`_gold_label`) and ``flagged``
    answers (given while or before the worker fell below the gold threshold).
    """
    now = now or utcnow()
    items = {it.id: it for it in batch.items}
    regular = sum(1 for it in items.values() if not it.is_gold)
    answers = list(db.session.execute(select(Answer.item_id, Answer.worker_id, Answer.payload, Answer.flagged)
                                      .where(Answer.item_id.in_(list(items)))))
    reservations = list(db.session.execute(select(Reservation.worker_id, Reservation.expires_at).where(
        Reservation.item_id.in_(list(items)), Reservation.answered_at.is_(None))))
    per_worker: dict[int, dict[str, int]] = {}

    def row(worker_id: int) -> dict[str, int]:
        return per_worker.setdefault(worker_id, {"done": 0, "reserved": 0, "expired": 0, "gold_correct": 0,
                                                 "gold_total": 0, "flagged": 0})

    for item_id, worker_id, payload, flagged in answers:
        counts = row(worker_id)
        counts["done"] += 1
        counts["flagged"] += bool(flagged)
        item = items[item_id]
        if item.is_gold and item.gold_answer:
            counts["gold_total"] += 1
            counts["gold_correct"] += _gold_label(batch.kind, payload, item.gold_answer)
    reserved = expired = 0
    for worker_id, expires_at in reservations:
        key = "reserved" if _aware(expires_at) > now else "expired"
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
    return {"batch": batch.id, "kind": batch.kind, "items": regular, "gold_items": len(items) - regular,
            "answers_per_item": n, "answers": len(answers),
            "regular_answers": sum(min(c, n) for c in usable.values()),
            "gold_answers": sum(1 for a in answers if items[a[0]].is_gold),
            "flagged_answers": sum(1 for a in answers if a[3]),
            "items_done": sum(1 for c in usable.values() if c >= n),
            "answers_needed": regular * batch.answers_per_item, "reserved": reserved, "expired": expired,
            "workers": {str(w): counts for w, counts in sorted(per_worker.items())}}


def worker_progress() -> list[dict[str, Any]]:
    """Every worker across batches: answers, flagged answers, gold accuracy and whether they are flagged.

    ``gold_accuracy`` is None until the worker answered a gold item; ``served`` is False once
    they fell below the threshold (they get no more tasks). ``sessions`` is how many visits
    (Prolific sessions, MTurk assignments) they opened, ``completed_sessions`` how many reached
    the completion step, ``refused_sessions`` how many got no work from the start (opened where
    a worker flagged in the same study came from; :mod:`annotation.sessions`).
    """
    sessions = {worker_id: (total, completed or 0, refused or 0)
                for worker_id, total, completed, refused in db.session.execute(
                    select(CrowdSession.worker_id, func.count(),
                           func.sum(case((CrowdSession.completed_at.is_not(None), 1), else_=0)),
                           func.sum(case((CrowdSession.flagged, 1), else_=0)))
                    .group_by(CrowdSession.worker_id))}
    counts = {worker_id: (total, flagged or 0) for worker_id, total, flagged in db.session.execute(
        select(Answer.worker_id, func.count(), func.sum(case((Answer.flagged, 1), else_=0)))
        .group_by(Answer.worker_id))}
    gold: dict[int, list[int]] = {}
    for worker_id, payload, gold_answer, kind in db.session.execute(
            select(Answer.worker_id, Answer.payload, BatchItem.gold_answer, Batch.kind)
            .join(BatchItem, Answer.item_id == BatchItem.id).join(Batch, BatchItem.batch_id == Batch.id)
            .where(BatchItem.is_gold.is_(True))):
        if gold_answer:
            gold.setdefault(worker_id, []).append(_gold_label(kind, payload, gold_answer))
    rows = []
    for worker in db.session.scalars(select(Worker).order_by(Worker.id)):
        total, flagged = counts.get(worker.id, (0, 0))
        opened, completed, refused = sessions.get(worker.id, (0, 0, 0))
        labels = gold.get(worker.id, [])
        rows.append({"worker": worker.id, "provider": worker.provider, "name": worker.external_id,
                     "answers": int(total), "flagged_answers": int(flagged), "gold_correct": sum(labels),
                     "gold_total": len(labels),
                     "gold_accuracy": round(sum(labels) / len(labels), 4) if labels else None,
                     "served": not worker.flagged, "sessions": int(opened),
                     "completed_sessions": int(completed), "refused_sessions": int(refused)})
    return rows


# ---------------------------------------------------------------------------------------------
# What the annotator's page shows: progress per batch, kinds with work, renewing a lapsed task


def batch_positions(worker: Worker | int, batch_ids: Iterable[int]) -> dict[int, dict[str, int]]:
    """Per batch: ``done`` (this worker's answers in it, every session) and ``total`` (done plus
    the items still open to them: regular items below N usable answers that they have not
    answered, and gold items they hold). ``total`` can shrink while they work, as others finish
    items; it never counts an item twice. Two grouped reads, whatever the batch size.
    """
    worker_id, ids = worker_id_of(worker), sorted(set(batch_ids))
    if not ids:
        return {}
    done = dict(db.session.execute(
        select(BatchItem.batch_id, func.count()).join(Answer, Answer.item_id == BatchItem.id)
        .where(Answer.worker_id == worker_id, BatchItem.batch_id.in_(ids)).group_by(BatchItem.batch_id)).all())
    answered = select(Answer.id).where(Answer.item_id == BatchItem.id, Answer.worker_id == worker_id).exists()
    holds = select(Reservation.id).where(Reservation.item_id == BatchItem.id, Reservation.worker_id == worker_id,
                                         Reservation.answered_at.is_(None)).exists()
    open_ = dict(db.session.execute(
        select(BatchItem.batch_id, func.count()).join(Batch, Batch.id == BatchItem.batch_id)
        .where(BatchItem.batch_id.in_(ids), ~answered,
               or_(and_(BatchItem.is_gold.is_(False), BatchItem.answers < Batch.answers_per_item),
                   and_(BatchItem.is_gold.is_(True), holds)))
        .group_by(BatchItem.batch_id)).all())
    return {b: {"done": int(done.get(b, 0)), "total": int(done.get(b, 0)) + int(open_.get(b, 0))} for b in ids}


def renew_reservation(worker: Worker | int, token: Any, now: datetime | None = None,
                      session: int | None = None) -> Task:
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
        if not _on_sqlite():
            _core(_LOCK_ITEMS, {"item_ids": [item.id]})
        db.session.refresh(item)
        counted = row.released_at is None
        if not counted and not item.is_gold and item.taken >= item.batch.answers_per_item:
            db.session.rollback()
            raise TaskError("Someone else took this card while your reservation had lapsed; fetch a new one", 409)
        row.expires_at, row.released_at = now + _reservation_ttl(), None
        db.session.flush()
        recount_items([item.id], locked=True)
        task = _task(row)
        db.session.commit()
    return task


_HAS_WALKABLE = (select(_items.c.id)
                 .where(_items.c.batch_id == bindparam("batch_id"), _items.c.is_gold.is_(False),
                        _items.c.taken < bindparam("n"), ~_held_by(bindparam("worker_id")))
                 .limit(1))


def open_kinds(worker: Worker | int, session: int | None = None, now: datetime | None = None) -> list[str]:
    """The task kinds, in :data:`TASK_KINDS` order, with work for this worker's session now: tasks it
    holds, or a free regular item of an open batch it has not answered or held. A read: nothing
    is reserved (a hold that lapsed but was not yet released by a fetch still counts as taken).
    """
    now = now or utcnow()
    worker_id = worker_id_of(worker)
    if _core(_WORKER_FLAGGED, {"worker_id": worker_id, "session_id": session}).scalar():
        return []
    kinds = []
    for kind in TASK_KINDS:
        if open_tasks(worker_id, kind, now, session):
            kinds.append(kind)
            continue
        for batch_id, n, _rate in _core(_OPEN_BATCHES, {"kind": kind}).all():
            if _core(_HAS_WALKABLE, {"batch_id": batch_id, "n": n, "worker_id": worker_id}).first() is not None:
                kinds.append(kind)
                break
    return kinds


def any_unfinished_batch() -> bool:
    """Whether any batch of any kind still wants answers (someone may hand theirs back)."""
    return any(_core(_OPEN_BATCHES, {"kind": kind}).first() is not None for kind in TASK_KINDS)


def preview_card() -> Card | None:
    """The card an MTurk preview shows: the first regular item of the oldest judge batch still open."""
    return db.session.scalar(
        select(Card).join(BatchItem, BatchItem.card_id == Card.id).join(Batch, Batch.id == BatchItem.batch_id)
        .where(Batch.kind == "judge", BatchItem.is_gold.is_(False), BatchItem.answers < Batch.answers_per_item)
        .order_by(Batch.id, BatchItem.id).limit(1))


def account_worker(person_id: int, username: str) -> Worker:
    """The invited worker of a logged-in account (``account:<username>``), made on first use."""
    worker = db.session.scalar(select(Worker).where(Worker.provider == "invite", Worker.person_id == person_id)
                               .order_by(Worker.id).limit(1))
    return worker or get_or_create_worker("invite", f"account:{username}", person_id=person_id)


def set_worker_flag(worker_id: int, flagged: bool) -> Worker:
    """A curator flags a worker (their answers leave aggregation, their open tasks go back to the
    pool: what failing gold does) or clears them (answers count again, they are served again).

    A cleared worker who is still below the gold threshold is flagged again at their next gold
    answer: clearing overrides the past, not the rule.
    """
    worker = db.session.get(Worker, worker_id)
    if worker is None:
        raise TaskError(f"No worker {worker_id}", 404)
    no_sync = {"synchronize_session": False}
    with one_writer():
        touched = sorted(set(db.session.scalars(select(Answer.item_id).where(Answer.worker_id == worker_id)))
                         | set(db.session.scalars(select(Reservation.item_id).where(
                             Reservation.worker_id == worker_id, Reservation.answered_at.is_(None)))))
        if touched and not _on_sqlite():
            _core(_LOCK_ITEMS, {"item_ids": touched})
        db.session.execute(update(Worker).where(Worker.id == worker_id).values(flagged=flagged).execution_options(**no_sync))
        db.session.execute(update(Answer).where(Answer.worker_id == worker_id).values(flagged=flagged)
                           .execution_options(**no_sync))
        if flagged:
            db.session.execute(delete(Reservation).where(Reservation.worker_id == worker_id,
                                                         Reservation.answered_at.is_(None)).execution_options(**no_sync))
        recount_items(touched, locked=True)
        db.session.commit()
    db.session.refresh(worker)
    return worker


@dataclass(frozen=True)
class SubmissionCheck:
    """What a researcher should do with one Prolific submission (participant id), and why."""

    participant: str
    decision: str  # "approve", "reject" or "unknown"
    reason: str
    sessions: int
    completed: int
    answers: int

    def as_json(self) -> dict[str, Any]:
        return {"participant": self.participant, "decision": self.decision, "reason": self.reason,
                "sessions": self.sessions, "completed": self.completed, "answers": self.answers}


def check_prolific_submissions(participants: Sequence[str], study: str | None = None) -> list[SubmissionCheck]:
    """For each Prolific participant id: approve when a session of theirs reached the completion
    step (where the completion code is handed out) with answers and they are not flagged on gold;
    reject when flagged; unknown when this tool never saw them or they gave no answer.
    ``study`` (a STUDY_ID) limits the sessions considered.
    """
    out = []
    for participant in dict.fromkeys(p.strip() for p in participants if p.strip()):
        worker = db.session.scalar(select(Worker).where(Worker.provider == "prolific", Worker.external_id == participant))
        if worker is None:
            out.append(SubmissionCheck(participant, "unknown", "never opened this study here", 0, 0, 0))
            continue
        query = select(CrowdSession).where(CrowdSession.worker_id == worker.id)
        if study:
            query = query.where(CrowdSession.study == study)
        sessions = list(db.session.scalars(query))
        ids = [s.id for s in sessions]
        answers = db.session.scalar(select(func.count()).select_from(Answer).where(
            Answer.worker_id == worker.id, Answer.session_id.in_(ids))) if ids else 0
        completed = sum(s.completed_at is not None for s in sessions)
        if worker.flagged or any(s.flagged for s in sessions):
            decision, reason = "reject", "flagged: failed the known-answer (gold) cards"
        elif not sessions:
            decision, reason = "unknown", "no session in this study"
        elif not completed:
            decision, reason = "unknown", "never reached the completion step (no completion code was shown)"
        elif not answers:
            decision, reason = "unknown", "reached the completion step without answering a card"
        else:
            decision, reason = "approve", f"completed with {answers} answers"
        out.append(SubmissionCheck(participant, decision, reason, len(sessions), completed, int(answers or 0)))
    return out
