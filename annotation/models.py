"""Crowd annotation rows: batches of items, workers, reservations, answers and aggregates.

The pure strategy (:mod:`annotation.assignment`, :mod:`annotation.aggregation`) never sees
these; the use cases (:mod:`annotation.reservations`, :mod:`annotation.answers`,
:mod:`annotation.results`) map them onto its records and back.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import (
    BigInteger,
    CheckConstraint,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.orm import Mapped, mapped_column, relationship

from core.db import JSONType, db, utcnow
from core.models import Card, Person

# confirm: a grid of cards shown as the orientation step would fix them; a worker taps what
# looks wrong (annotation.grids).
TASK_KINDS: tuple[str, ...] = ("judge", "crop", "confirm")
PROVIDERS: tuple[str, ...] = ("invite", "prolific", "mturk")
# escalated: a confirm grid's crowd could not agree on a card; it goes to a one-card judge task
# (people judge it from scratch) rather than to a curator's dispute queue.
AGGREGATE_STATES: tuple[str, ...] = ("approved", "needs_curator", "escalated")


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class Batch(db.Model):
    __tablename__ = "crowd_batches"
    __table_args__ = (
        CheckConstraint(_in("kind", TASK_KINDS), name="kind"),
        CheckConstraint("answers_per_item >= 1", name="answers_per_item"),
        CheckConstraint("gold_rate >= 0 AND gold_rate <= 1", name="gold_rate"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    kind: Mapped[str] = mapped_column(String(10))
    answers_per_item: Mapped[int] = mapped_column(Integer, default=3)
    gold_rate: Mapped[float] = mapped_column(Float, default=0.1)
    created_by: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    items: Mapped[list[BatchItem]] = relationship(back_populates="batch", cascade="all, delete-orphan", order_by="BatchItem.id")


class BatchItem(db.Model):
    """One card to answer in a batch, with its slot counters.

    ``answers`` (usable answers: not flagged) and ``taken`` (usable answers + open
    reservations) are a cache of counts over this item's rows, recounted from those rows by
    :func:`annotation.queries.recount_items` in the same transaction as every change to them. They let fetch-next
    walk ``ix_crowd_batch_items_open`` (most taken first, then ``rank``, the batch's shuffle:
    :func:`annotation.assignment.item_rank`) and stop at the first open item, whatever the
    batch's size.
    """

    __tablename__ = "crowd_batch_items"
    __table_args__ = (
        UniqueConstraint("batch_id", "card_id", name="crowd_item_batch_card"),
        Index("ix_crowd_batch_items_open", "batch_id", "is_gold", "taken", "rank"),
        Index("ix_crowd_batch_items_unfinished", "batch_id", "is_gold", "answers"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    batch_id: Mapped[int] = mapped_column(ForeignKey("crowd_batches.id", ondelete="CASCADE"), index=True)
    card_id: Mapped[int] = mapped_column(ForeignKey("cards.id", ondelete="CASCADE"), index=True)
    is_gold: Mapped[bool] = mapped_column(default=False)
    gold_answer: Mapped[dict[str, Any] | None] = mapped_column(JSONType)
    answers: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    taken: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    rank: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")
    # confirm items: the orientation flags (as scanned) the grid applies before showing the card,
    # fixed when the batch is made, so taps always refer to the picture the worker saw (the
    # step's proposal may change on a rerun; a gold item shows a deliberately wrong one).
    shown: Mapped[dict[str, Any] | None] = mapped_column(JSONType)

    batch: Mapped[Batch] = relationship(back_populates="items")
    card: Mapped[Card] = relationship()


class Worker(db.Model):
    """Someone answering tasks: an invited annotator, a Prolific participant or an MTurk worker."""

    __tablename__ = "crowd_workers"
    __table_args__ = (
        CheckConstraint(_in("provider", PROVIDERS), name="provider"),
        UniqueConstraint("provider", "external_id", name="crowd_worker_provider_external"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    provider: Mapped[str] = mapped_column(String(10))
    external_id: Mapped[str] = mapped_column(String(200))
    person_id: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    token: Mapped[str] = mapped_column(String(64), unique=True)  # invite links: the whole credential
    flagged: Mapped[bool] = mapped_column(default=False)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    person: Mapped[Person | None] = relationship()


class CrowdSession(db.Model):
    """One visit of a worker through a provider: what reservations, undo and completion are bound to.

    ``external_id`` is the provider's own session key: Prolific's ``SESSION_ID``, MTurk's
    ``assignmentId``, or ``"invite"`` (the invite link is the whole credential, so an invited
    annotator has one session). It is unique per provider, so a session opened by one
    participant can never be reopened under another participant's id. ``study`` is Prolific's
    ``STUDY_ID`` or MTurk's ``hitId`` (empty for invites): the unit of the creation limits.
    ``address`` is a keyed hash of the client address (the address itself is never stored),
    used only for the per-address limits. ``flagged`` marks a session refused work because a
    worker flagged on gold in the same study came from the same address.
    """

    __tablename__ = "crowd_sessions"
    __table_args__ = (
        CheckConstraint(_in("provider", PROVIDERS), name="provider"),
        UniqueConstraint("provider", "external_id", name="crowd_session_provider_external"),
        Index("ix_crowd_sessions_address", "address", "created_at"),
        Index("ix_crowd_sessions_study", "provider", "study", "created_at"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    worker_id: Mapped[int] = mapped_column(ForeignKey("crowd_workers.id", ondelete="CASCADE"), index=True)
    provider: Mapped[str] = mapped_column(String(10))
    external_id: Mapped[str] = mapped_column(String(200))
    study: Mapped[str] = mapped_column(String(200), default="", server_default="")
    address: Mapped[str] = mapped_column(String(64), default="", server_default="")
    flagged: Mapped[bool] = mapped_column(default=False)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    completed_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))

    worker: Mapped[Worker] = relationship()


class Reservation(db.Model):
    """An item handed to a worker. Open while ``expires_at`` is ahead and ``answered_at`` is empty.

    Kept after the answer (``answered_at`` set) so a late or replayed post gets an exact reason.
    ``released_at`` is set when a lapsed, unanswered reservation stopped counting toward its
    item's ``taken`` (the sweep in :mod:`annotation.reservations`; renewing it clears it again).
    """

    __tablename__ = "crowd_reservations"
    __table_args__ = (
        UniqueConstraint("item_id", "worker_id", name="crowd_reservation_item_worker"),
        # Counted holds only: a worker's open tasks, and the holds due to lapse.
        Index(
            "ix_crowd_reservations_held",
            "worker_id",
            "expires_at",
            sqlite_where=text("answered_at IS NULL AND released_at IS NULL"),
            postgresql_where=text("answered_at IS NULL AND released_at IS NULL"),
        ),
        Index(
            "ix_crowd_reservations_lapsing",
            "expires_at",
            sqlite_where=text("answered_at IS NULL AND released_at IS NULL"),
            postgresql_where=text("answered_at IS NULL AND released_at IS NULL"),
        ),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    item_id: Mapped[int] = mapped_column(ForeignKey("crowd_batch_items.id", ondelete="CASCADE"), index=True)
    worker_id: Mapped[int] = mapped_column(ForeignKey("crowd_workers.id", ondelete="CASCADE"), index=True)
    # The session that holds it (None: in-process callers such as the simulator, never the web).
    # No foreign key: SQLite cannot add one to an existing table without copying it (see the
    # 0005 migration); a session is deleted only with its worker, which takes these rows along.
    session_id: Mapped[int | None] = mapped_column(Integer, index=True)
    token: Mapped[str] = mapped_column(String(64), unique=True)  # names the task in image and submit URLs
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    answered_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    released_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))

    item: Mapped[BatchItem] = relationship()
    worker: Mapped[Worker] = relationship()


class Answer(db.Model):
    __tablename__ = "crowd_answers"
    __table_args__ = (UniqueConstraint("item_id", "worker_id", name="crowd_answer_item_worker"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    item_id: Mapped[int] = mapped_column(ForeignKey("crowd_batch_items.id", ondelete="CASCADE"), index=True)
    worker_id: Mapped[int] = mapped_column(ForeignKey("crowd_workers.id", ondelete="CASCADE"), index=True)
    # The session that gave it: only that session may undo it or count it as its progress
    # (no foreign key, as on reservations).
    session_id: Mapped[int | None] = mapped_column(Integer, index=True)
    payload: Mapped[dict[str, Any]] = mapped_column(JSONType)
    submitted_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    idempotency_key: Mapped[str] = mapped_column(String(80), unique=True)
    flagged: Mapped[bool] = mapped_column(default=False)

    item: Mapped[BatchItem] = relationship()
    worker: Mapped[Worker] = relationship()


class Aggregate(db.Model):
    """The crowd's answer for one card in one batch; ``approved`` ones feed the pipeline."""

    __tablename__ = "crowd_aggregates"
    __table_args__ = (
        CheckConstraint(_in("kind", TASK_KINDS), name="kind"),
        CheckConstraint(_in("state", AGGREGATE_STATES), name="state"),
        UniqueConstraint("batch_id", "card_id", name="crowd_aggregate_batch_card"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    batch_id: Mapped[int] = mapped_column(ForeignKey("crowd_batches.id", ondelete="CASCADE"), index=True)
    card_id: Mapped[int] = mapped_column(ForeignKey("cards.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(10))
    posterior: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)
    label: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)
    confident: Mapped[bool] = mapped_column(default=False)
    state: Mapped[str] = mapped_column(String(20))
    reasons: Mapped[str] = mapped_column(Text, default="")  # why it waits for a curator
    answers: Mapped[int] = mapped_column(Integer, default=0)
    # Set when a curator decided a disputed aggregate: their label is the card's truth.
    resolved_by: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    # indexed: the background worker's change mark reads the newest (runs.worker.change_mark)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, onupdate=utcnow, index=True)


class GoldAnswer(db.Model):
    """A known answer a curator made for a card; new batches mix these in as gold items."""

    __tablename__ = "crowd_gold_answers"
    __table_args__ = (
        CheckConstraint(_in("kind", TASK_KINDS), name="kind"),
        UniqueConstraint("card_id", "kind", name="crowd_gold_card_kind"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    card_id: Mapped[int] = mapped_column(ForeignKey("cards.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(10))
    answer: Mapped[dict[str, Any]] = mapped_column(JSONType)
    made_by: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
