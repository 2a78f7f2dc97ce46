"""The crowd's prebuilt SQL statements and the small helpers that run them.

Hot statements are built once with bound parameters and run on the session's connection with
:func:`run_prebuilt`: building a select() costs about as much Python as running it, ORM row
handling more (why the fetch path is built this way: :mod:`annotation.reservations`). Every write
that changes an item's answers or reservations calls :func:`recount_items` before committing.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import Integer, and_, bindparam, func, inspect as sa_inspect, or_, select

from core.db import db
from core.models import Card

from .labels import batch_takes_new_tasks
from .models import Answer, Batch, BatchItem, CrowdSession, Reservation, Worker


def as_utc(moment: datetime) -> datetime:
    # SQLite hands back naive datetimes for DateTime(timezone=True); they were stored as UTC.
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


def worker_id_of(worker: Worker | int) -> int:
    """The worker's id without a query, even when the row is expired after a rolled-back read."""
    if isinstance(worker, int):
        return worker
    identity = sa_inspect(worker).identity
    return int(identity[0]) if identity else int(worker.id)


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
        select(reservations.c.id)
        .where(reservations.c.item_id == item, reservations.c.worker_id == worker, _held(reservations))
        .exists(),
    )


def _recount_statement() -> Any:
    usable = (
        select(func.count())
        .select_from(_answers)
        .where(_answers.c.item_id == _items.c.id, _answers.c.flagged.is_(False))
        .scalar_subquery()
    )
    held = select(func.count()).select_from(_reservations).where(_reservations.c.item_id == _items.c.id, _HELD).scalar_subquery()
    return (
        _items.update().where(_items.c.id.in_(bindparam("item_ids", expanding=True))).values(answers=usable, taken=usable + held)
    )


RECOUNT = _recount_statement()
# FOR NO KEY UPDATE: it serializes writers of one item, but not the KEY SHARE locks that
# inserting an answer or a reservation (foreign keys to the item) takes.
LOCK_ITEMS = (
    select(_items.c.id)
    .where(_items.c.id.in_(bindparam("item_ids", expanding=True)))
    .order_by(_items.c.id)
    .with_for_update(key_share=True)
)
LOCK_FREE_ITEMS = (
    select(_items.c.id)
    .where(_items.c.id.in_(bindparam("item_ids", expanding=True)))
    .order_by(_items.c.id)
    .with_for_update(key_share=True, skip_locked=True)
)
SWEEP_LIMIT = 500  # lapsed holds released per fetch; the next fetch releases the rest
LAPSED_ITEMS = select(_reservations.c.item_id).where(_HELD, _reservations.c.expires_at <= bindparam("now")).limit(SWEEP_LIMIT)
RELEASE_LAPSED = (
    _reservations.update()
    .where(
        _reservations.c.item_id.in_(bindparam("item_ids", expanding=True)), _HELD, _reservations.c.expires_at <= bindparam("now")
    )
    .values(released_at=bindparam("now"))
)

OPEN_TASKS = (
    select(Reservation.token, BatchItem.batch_id, Batch.kind, BatchItem.card_id, Card.width, Card.height, Reservation.expires_at)
    .join(BatchItem, Reservation.item_id == BatchItem.id)
    .join(Batch, BatchItem.batch_id == Batch.id)
    .join(Card, BatchItem.card_id == Card.id)
    .where(
        Reservation.worker_id == bindparam("worker_id"),
        Reservation.session_id.is_not_distinct_from(bindparam("session_id", type_=Integer)),
        Reservation.answered_at.is_(None),
        Reservation.released_at.is_(None),
        Batch.kind == bindparam("kind"),
        Reservation.expires_at > bindparam("now"),
    )
    .order_by(Reservation.created_at, Reservation.id)
)
# Refused work: the worker is flagged on gold (in any session), or this session inherited a flag
# (annotation.sessions: a flagged worker of the same study came from the same address).
WORKER_FLAGGED = select(
    or_(
        Worker.flagged,
        select(CrowdSession.id)
        .where(CrowdSession.id == bindparam("session_id", type_=Integer), CrowdSession.flagged.is_(True))
        .exists(),
    )
).where(Worker.id == bindparam("worker_id"))
# A session's progress: only its own answers (another session of the worker is not shown).
ANSWER_COUNT = (
    select(func.count())
    .select_from(Answer)
    .where(
        Answer.worker_id == bindparam("worker_id"), Answer.session_id.is_not_distinct_from(bindparam("session_id", type_=Integer))
    )
)
# Batches with a regular item below N usable answers, not paused or closed by a curator
# (annotation.labels): one index seek per batch.
OPEN_BATCHES = (
    select(Batch.id, Batch.answers_per_item, Batch.gold_rate)
    .where(
        Batch.kind == bindparam("kind"),
        select(_items.c.id)
        .where(_items.c.batch_id == Batch.id, _items.c.is_gold.is_(False), _items.c.answers < Batch.answers_per_item)
        .exists(),
        batch_takes_new_tasks(),  # after: only batches with open items read the audit trail
    )
    .order_by(Batch.id)
)
# The walk: open regular items this worker may take, in the pure strategy's order, on the
# index (batch_id, is_gold, taken, rank) read backwards. ``mine`` is this worker's released
# (lapsed) reservation of the item, renewed rather than duplicated.
_mine = _reservations.alias("mine")
OPEN_ITEMS = (
    select(
        _items.c.id,
        _items.c.card_id,
        Card.width,
        Card.height,
        _mine.c.id.label("mine"),
        _mine.c.token.label("mine_token"),
        _mine.c.session_id.label("mine_session"),
    )
    .join(Card, _items.c.card_id == Card.id)
    .outerjoin(_mine, and_(_mine.c.item_id == _items.c.id, _mine.c.worker_id == bindparam("worker_id")))
    .where(
        _items.c.batch_id == bindparam("batch_id"),
        _items.c.is_gold.is_(False),
        _items.c.taken < bindparam("n"),
        ~_held_by(bindparam("worker_id")),
    )
    .order_by(_items.c.taken.desc(), _items.c.rank.desc())
    .limit(bindparam("limit", type_=Integer))
)
OPEN_ITEMS_LOCKED = OPEN_ITEMS.with_for_update(key_share=True, skip_locked=True, of=_items)
# Gold is never capped at N: every gold item this worker has not seen, with how often it was answered.
OPEN_GOLD = (
    select(
        _items.c.id,
        _items.c.card_id,
        _items.c.answers,
        Card.width,
        Card.height,
        _mine.c.id.label("mine"),
        _mine.c.token.label("mine_token"),
        _mine.c.session_id.label("mine_session"),
    )
    .join(Card, _items.c.card_id == Card.id)
    .outerjoin(_mine, and_(_mine.c.item_id == _items.c.id, _mine.c.worker_id == bindparam("worker_id")))
    .where(_items.c.batch_id == bindparam("batch_id"), _items.c.is_gold.is_(True), ~_held_by(bindparam("worker_id")))
)


# How many items of the batch this worker answered or holds: the key of the gold draw. Driven
# from the worker's own rows (their indexes) with the item's batch looked up per row: a join
# lets SQLite's planner start from the batch's items instead. The two sets are disjoint, since
# an answer closes its reservation and an undo deletes the answer before renewing it.
def _batch_of(item: Any) -> Any:
    return select(_items.c.batch_id).where(_items.c.id == item).scalar_subquery()


SERVED = select(
    select(func.count())
    .select_from(_answers)
    .where(_answers.c.worker_id == bindparam("worker_id"), _batch_of(_answers.c.item_id) == bindparam("batch_id"))
    .scalar_subquery()
    + select(func.count())
    .select_from(_reservations)
    .where(
        _reservations.c.worker_id == bindparam("worker_id"), _HELD, _batch_of(_reservations.c.item_id) == bindparam("batch_id")
    )
    .scalar_subquery()
)
# Why a batch has nothing for this worker: its unfinished regular items this worker has not
# touched, and the earliest lapse of a hold on them (they are all held by others, else the
# walk would have found one).
UNFINISHED = (
    select(func.count(_items.c.id.distinct()), func.min(_reservations.c.expires_at))
    .select_from(_items)
    .outerjoin(_reservations, and_(_reservations.c.item_id == _items.c.id, _HELD))
    .where(
        _items.c.batch_id == bindparam("batch_id"),
        _items.c.is_gold.is_(False),
        _items.c.answers < bindparam("n"),
        ~_held_by(bindparam("worker_id")),
    )
)
ANY_UNFINISHED = (
    select(_items.c.id)
    .where(_items.c.batch_id == bindparam("batch_id"), _items.c.is_gold.is_(False), _items.c.answers < bindparam("n"))
    .limit(1)
)
INSERT_RESERVATION = _reservations.insert()
RENEW_RESERVATION = (
    _reservations.update()
    .where(_reservations.c.id == bindparam("reservation_id"))
    .values(
        expires_at=bindparam("expires"),
        answered_at=None,
        released_at=None,
        created_at=bindparam("created"),
        session_id=bindparam("holder"),
        token=bindparam("new_token"),
    )
)


ANSWER_BY_KEY = select(Answer.id, Answer.worker_id, Answer.session_id).where(Answer.idempotency_key == bindparam("key"))
RESERVATION_TO_ANSWER = (
    select(
        Reservation.id,
        Reservation.worker_id,
        Reservation.session_id,
        Reservation.answered_at,
        Reservation.released_at,
        Reservation.expires_at,
        Reservation.item_id,
        BatchItem.is_gold,
        Batch.kind,
        Card.width,
        Card.height,
    )
    .join(BatchItem, Reservation.item_id == BatchItem.id)
    .join(Batch, BatchItem.batch_id == Batch.id)
    .join(Card, BatchItem.card_id == Card.id)
    .where(Reservation.token == bindparam("token"))
)
RESERVATION_STATE = select(
    Reservation.id,
    Reservation.worker_id,
    Reservation.session_id,
    Reservation.answered_at,
    Reservation.released_at,
    Reservation.expires_at,
).where(Reservation.id == bindparam("reservation_id"))
# Matches only while the reservation is this worker's session's, unanswered and still counted
# (not lapsed, not released by a sweep): the claim and the check in one.
CLAIM_RESERVATION = (
    _reservations.update()
    .where(
        _reservations.c.id == bindparam("reservation_id"),
        _reservations.c.worker_id == bindparam("claimant"),
        _reservations.c.session_id.is_not_distinct_from(bindparam("claimant_session", type_=Integer)),
        _HELD,
        _reservations.c.expires_at > bindparam("at"),
    )
    .values(answered_at=bindparam("at"))
)
INSERT_ANSWER = _answers.insert()


HAS_WALKABLE = (
    select(_items.c.id)
    .where(
        _items.c.batch_id == bindparam("batch_id"),
        _items.c.is_gold.is_(False),
        _items.c.taken < bindparam("n"),
        ~_held_by(bindparam("worker_id")),
    )
    .limit(1)
)


def on_sqlite() -> bool:
    return db.session.get_bind().dialect.name == "sqlite"


def run_prebuilt(statement: Any, params: Mapping[str, Any]) -> Any:
    """Run a prebuilt statement on the session's connection: plain rows, none of the ORM's row handling.

    Same transaction as the session (a read-only one inside :func:`core.db.read_only`).
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
    if not locked and not on_sqlite():
        run_prebuilt(LOCK_ITEMS, {"item_ids": ids})
    run_prebuilt(RECOUNT, {"item_ids": ids})
