"""Curator review rows: one review per card, orientation overrides, the fitted grade and upright models.

A card's *automatic* grade is a ``grade`` stage result (``core.models.StageResult``); the
curator's decision and the card's final grade live in :class:`CardReview`. Every change to a
grade, a decision or a crowd annotation is also written to the append-only audit trail
(:class:`core.audit.AuditEvent`), which the kernel keeps because the people admin writes to it too.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import CheckConstraint, DateTime, Float, ForeignKey, Index, Integer, String, Text
from sqlalchemy.orm import Mapped, mapped_column, relationship

from core.db import JSONType, db, utcnow
from core.models import Card, Person

# The paper's three categories, best first. "few" and "some" are artifact levels.
GRADES: tuple[str, ...] = ("few", "some", "failure")
GRADE_NAMES: dict[str, str] = {"few": "few artifacts", "some": "some artifacts", "failure": "failure"}
# pending: not yet seen by a curator; accepted: the automatic grade stands; changed: the curator
# set another grade; sent_back: returned to the crowd for new crop boxes / judgements;
# rejected: never to be released.
DECISIONS: tuple[str, ...] = ("pending", "accepted", "changed", "sent_back", "rejected")


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class CardReview(db.Model):
    """The curator's view of one card. ``version`` is the optimistic lock: a decision posted
    against an older version is refused with a conflict instead of overwriting a colleague."""

    __tablename__ = "card_reviews"
    __table_args__ = (
        # The queue's order: a page of 50 from 250,000 reviews reads 50 index entries (13 ms
        # measured on SQLite) instead of sorting the table (125 ms).
        # SQLite sorts NULLs last in DESC by default and serves "DESC NULLS LAST" from this index;
        # PostgreSQL needs the NULLS LAST spelled out in the index (SQLite refuses it there).
        Index("ix_card_reviews_queue", "decision", db.text("uncertainty DESC"), "card_id").ddl_if(dialect="sqlite"),
        Index("ix_card_reviews_queue", "decision", db.text("uncertainty DESC NULLS LAST"), "card_id").ddl_if(
            dialect="postgresql"
        ),
        CheckConstraint(_in("decision", DECISIONS), name="decision"),
        CheckConstraint(f"grade IS NULL OR {_in('grade', GRADES)}", name="grade"),
        CheckConstraint(f"auto_grade IS NULL OR {_in('auto_grade', GRADES)}", name="auto_grade"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    card_id: Mapped[int] = mapped_column(ForeignKey("cards.id", ondelete="CASCADE"), unique=True)
    auto_grade: Mapped[str | None] = mapped_column(String(10))  # the grade stage's outcome when last synced
    auto_param_hash: Mapped[str | None] = mapped_column(String(32))
    uncertainty: Mapped[float | None] = mapped_column(Float)  # 0 = sure .. 1 = on a threshold; sorts the queue
    grade: Mapped[str | None] = mapped_column(String(10), index=True)  # the card's final grade
    decision: Mapped[str] = mapped_column(String(12), default="pending", index=True)
    note: Mapped[str] = mapped_column(Text, default="")
    reviewer_id: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    decided_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    version: Mapped[int] = mapped_column(Integer, default=1)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, onupdate=utcnow)
    # The results an accept or grade change was given (runs.card_state.results_fingerprint): a
    # result recomputed since outdates the decision. None: pending, sent back, rejected, or
    # decided before revision 0014 (then compared by time).
    accepted_results: Mapped[dict[str, Any] | None] = mapped_column(JSONType)

    card: Mapped[Card] = relationship()
    reviewer: Mapped[Person | None] = relationship()

    # SQLAlchemy bumps the version on every flush and refuses a stale row (StaleDataError).
    __mapper_args__ = {"version_id_col": version}


class OrientationOverride(db.Model):
    """A curator's word on a card's orientation, flag by flag (null: not overridden, the step's
    or the crowd's value stands). One row per card, replaced by the next override; every
    change is also an audit event (entity ``orientation``). See :mod:`pipeline.decided_orientation`."""

    __tablename__ = "orientation_overrides"

    id: Mapped[int] = mapped_column(primary_key=True)
    card_id: Mapped[int] = mapped_column(ForeignKey("cards.id", ondelete="CASCADE"), unique=True)
    upside_down: Mapped[bool | None] = mapped_column()
    inverted: Mapped[bool | None] = mapped_column()
    swapped: Mapped[bool | None] = mapped_column()
    curator_id: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    note: Mapped[str] = mapped_column(Text, default="")
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, onupdate=utcnow)

    curator: Mapped[Person | None] = relationship()

    @property
    def curator_name(self) -> str | None:
        return self.curator.username if self.curator is not None else None


class GradeModel(db.Model):
    """Thresholds of the automatic grader, fitted to curator labels (``keystone grade fit``).

    The newest row is the active one; older rows stay so a grade can always be traced to the
    thresholds that produced it (the grade stage's parameter hash covers the thresholds).
    """

    __tablename__ = "grade_models"

    id: Mapped[int] = mapped_column(primary_key=True)
    thresholds: Mapped[dict[str, Any]] = mapped_column(JSONType)
    fitted_on: Mapped[int] = mapped_column(Integer, default=0)  # curator labels used
    evaluation: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)  # held-out agreement
    created_by: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class UprightHeadFit(db.Model):
    """A refit of the orientation step's learned upright / positive heads on a collection's own
    decided cards (``keystone orientation fit``; :mod:`review.upright_fit`).

    ``collection_id`` None: fitted on every collection, used where a collection has no refit of
    its own. The newest row for a collection is the one in force; older rows stay so a decision
    can be traced to the head that made it (the head's ``version`` reaches the orientation
    step's inputs, so a refit changes decisions only on the next run, which lists them)."""

    __tablename__ = "upright_head_fits"

    id: Mapped[int] = mapped_column(primary_key=True)
    collection_id: Mapped[int | None] = mapped_column(ForeignKey("collections.id", ondelete="CASCADE"), index=True)
    version: Mapped[str] = mapped_column(String(80), unique=True)
    head: Mapped[dict[str, Any]] = mapped_column(JSONType)  # pipeline.upright.UprightHead.as_dict()
    fitted_on: Mapped[int] = mapped_column(Integer, default=0)  # decided cards used
    evaluation: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)  # held out, before and after
    created_by: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
