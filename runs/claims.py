"""One driver per card-stage: claims in the database with a heartbeat and an expiry.

Two ``keystone run`` at once used to plan the same cards and compute each twice (and on
PostgreSQL the slower one died on the unique key of ``stage_results``). Now a driver claims
the cards of a stage in small batches before it computes them: a ``stage_claims`` row per
(card, stage), unique, so whoever inserts it first owns the card until it writes the result
(the claim is deleted in the same transaction as the result is written) or the claim expires.

- A claim lives ``ttl_s`` seconds past its last heartbeat. A live driver renews all of its
  claims from a background thread every ``ttl_s / 4``, so a card that computes for an hour
  stays claimed; a killed driver stops renewing and its claims lapse after at most ``ttl_s``,
  when the next driver takes them over.
- Taking claims is one short write transaction per batch. On SQLite it begins IMMEDIATE behind
  :func:`core.db.one_writer`, so claimers queue. On PostgreSQL it is ``INSERT ... ON CONFLICT
  DO NOTHING`` for new claims, and lapsed claims are taken over, renewed and released through
  ``SELECT ... FOR UPDATE SKIP LOCKED``, so no claim statement waits on a row another
  transaction holds, except the insert waiting for a concurrent insert or release of the same
  card to commit; those never wait in turn, and batches are claimed in card order, so two
  drivers cannot deadlock.
- After claiming, the driver looks again at the card's result for this stage and parameters:
  if it changed since the driver planned the stage, another run finished the card meanwhile
  (and released its claim), so the claim is dropped and the card is not computed again.

Clocks: ``expires_at`` is written by the claiming machine's clock (UTC). Drivers on several
machines sharing one PostgreSQL need clocks in step to well within ``ttl_s`` (NTP does).
A driver that is alive but frozen longer than ``ttl_s`` (a stopped process) loses its claims;
the card may then be computed twice, and both writes land on the same result row.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import (
    DateTime,
    Delete,
    ForeignKey,
    Index,
    String,
    UniqueConstraint,
    delete,
    select,
    update,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Mapped, mapped_column

from core.db import db, one_writer, utcnow

log = logging.getLogger(__name__)

DEFAULT_CLAIM_TTL_S = 120.0
# Cards claimed per write transaction: small enough that a second run finds work beside the
# first, large enough that claiming costs little next to computing.
DEFAULT_CLAIM_BATCH = 16

# What a stage result looked like when the driver planned the stage: its status and start
# time, or None when there was none. A different one after claiming means another run wrote it.
ResultFingerprint = tuple[str, Any] | None


class StageClaim(db.Model):
    """A driver's claim on one card for one stage, good until ``expires_at``."""

    __tablename__ = "stage_claims"
    __table_args__ = (
        UniqueConstraint("card_id", "stage", name="card_stage"),
        Index("ix_stage_claims_driver", "driver"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    card_id: Mapped[int] = mapped_column(ForeignKey("cards.id", ondelete="CASCADE"))
    stage: Mapped[str] = mapped_column(String(30))
    param_hash: Mapped[str] = mapped_column(String(32))
    driver: Mapped[str] = mapped_column(String(120))  # host:pid:random, see new_driver_id
    claimed_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    heartbeat_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    expires_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


def new_driver_id() -> str:
    """``host:pid:random``: who holds a claim, readable by an operator, unique per run."""
    return f"{socket.gethostname()[:60]}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


@dataclass
class ClaimRound:
    """What one attempt to claim a batch of cards found."""

    claimed: list[int] = field(default_factory=list)  # this driver holds them now: compute them
    taken_over: list[int] = field(default_factory=list)  # of claimed, lapsed claims of another driver
    finished_elsewhere: list[int] = field(default_factory=list)  # another run wrote them since planning
    held: dict[int, str] = field(default_factory=dict)  # card -> the live driver that holds it


def _insert(dialect: str) -> Any:
    return postgresql.insert if dialect == "postgresql" else sqlite.insert


class Driver:
    """One run's identity, claim lifetime and heartbeat. Use :meth:`running` around a run."""

    def __init__(self, engine: Engine, ttl_s: float = DEFAULT_CLAIM_TTL_S, driver_id: str | None = None) -> None:
        if ttl_s <= 0:
            raise ValueError(f"claim ttl must be positive seconds, got {ttl_s}")
        self.engine = engine
        self.ttl_s = float(ttl_s)
        self.id = driver_id or new_driver_id()
        self.heartbeats = 0
        self._stop = threading.Event()

    @property
    def heartbeat_interval_s(self) -> float:
        # Four renewals per lifetime: a claim survives three missed beats (a database busy
        # for a while, a long pause of the interpreter) before anyone may take it.
        return self.ttl_s / 4

    def expiry(self, now: datetime) -> datetime:
        return now + timedelta(seconds=self.ttl_s)

    @contextmanager
    def running(self) -> Iterator[Driver]:
        """Renew this driver's claims in a background thread; release whatever it still holds
        on the way out (a finished run holds nothing; an interrupted one frees its cards now
        rather than after ``ttl_s``)."""
        self._stop.clear()
        beat = threading.Thread(target=self._beat, name=f"claim-heartbeat-{self.id}", daemon=True)
        beat.start()
        try:
            yield self
        finally:
            self._stop.set()
            beat.join(timeout=60)
            # A write cut short (an exception, Ctrl+C) may still hold SQLite's write lock.
            db.session.rollback()
            self.release_all()

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_interval_s):
            try:
                self.renew()
            except SQLAlchemyError as exc:  # a busy or unreachable database: try again next beat
                log.warning("claim heartbeat of %s failed: %s", self.id, exc)

    def renew(self) -> int:
        """Push the expiry of every claim this driver holds ``ttl_s`` past now; returns how many."""
        now = utcnow()
        mine = select(StageClaim.id).where(StageClaim.driver == self.id).with_for_update(skip_locked=True)
        with self.engine.begin() as connection:
            renewed = connection.execute(
                update(StageClaim)
                .where(StageClaim.id.in_(mine.scalar_subquery()))
                .values(heartbeat_at=now, expires_at=self.expiry(now))
                .execution_options(synchronize_session=False)
            ).rowcount
        self.heartbeats += 1
        return renewed

    def release_statement(self, stage: str, card_ids: Iterable[int]) -> Delete:
        """Delete this driver's claims on these cards (run it in the transaction that writes their results)."""
        mine = (
            select(StageClaim.id)
            .where(StageClaim.driver == self.id, StageClaim.stage == stage, StageClaim.card_id.in_(list(card_ids)))
            .with_for_update(skip_locked=True)
        )
        return delete(StageClaim).where(StageClaim.id.in_(mine.scalar_subquery())).execution_options(synchronize_session=False)

    def release_all(self) -> None:
        try:
            with self.engine.begin() as connection:
                connection.execute(delete(StageClaim).where(StageClaim.driver == self.id))
        except SQLAlchemyError as exc:  # the claims lapse on their own after ttl_s
            log.warning("could not release the claims of %s: %s", self.id, exc)

    def claim(self, stage: str, param_hash: str, card_ids: list[int], seen: dict[int, ResultFingerprint]) -> ClaimRound:
        """Claim ``card_ids`` for ``stage`` in one short write transaction.

        ``seen`` is each card's result fingerprint (for this stage and parameters) when the
        driver planned the stage; a card whose result changed since is left to the run that
        wrote it. Cards are claimed in id order, the lock order every driver follows.
        """
        ids = sorted(set(card_ids))
        result = ClaimRound()
        if not ids:
            return result
        session = db.session()
        with one_writer(session):
            connection = session.connection()
            now = utcnow()
            dialect = connection.dialect.name
            # Lapsed claims of other drivers first: take them over in place.
            lapsed = (
                select(StageClaim.id)
                .where(
                    StageClaim.stage == stage,
                    StageClaim.card_id.in_(ids),
                    StageClaim.driver != self.id,
                    StageClaim.expires_at < now,
                )
                .with_for_update(skip_locked=True)
            )
            taken = (
                connection.execute(
                    update(StageClaim)
                    .where(StageClaim.id.in_(lapsed.scalar_subquery()))
                    .values(driver=self.id, param_hash=param_hash, claimed_at=now, heartbeat_at=now, expires_at=self.expiry(now))
                    .returning(StageClaim.card_id)
                    .execution_options(synchronize_session=False)
                )
                .scalars()
                .all()
            )
            rows = [
                {
                    "card_id": card_id,
                    "stage": stage,
                    "param_hash": param_hash,
                    "driver": self.id,
                    "claimed_at": now,
                    "heartbeat_at": now,
                    "expires_at": self.expiry(now),
                }
                for card_id in ids
            ]
            connection.execute(
                _insert(dialect)(StageClaim).values(rows).on_conflict_do_nothing(index_elements=["card_id", "stage"])
            )
            holders = dict(
                connection.execute(
                    select(StageClaim.card_id, StageClaim.driver).where(StageClaim.stage == stage, StageClaim.card_id.in_(ids))
                ).all()
            )
            mine = [card_id for card_id in ids if holders.get(card_id) == self.id]
            # A card with no claim at all lost it between the insert and this read (PostgreSQL):
            # its holder just released it. Treat it as held; the next round sees why.
            result.held = {
                card_id: holders.get(card_id, "another run (released while claiming)")
                for card_id in ids
                if holders.get(card_id) != self.id
            }
            changed = self._finished_since(connection, stage, param_hash, mine, seen)
            if changed:
                connection.execute(self.release_statement(stage, changed))
            session.commit()
        result.finished_elsewhere = sorted(changed)
        result.claimed = [card_id for card_id in mine if card_id not in changed]
        result.taken_over = sorted(set(taken) & set(result.claimed))
        return result

    @staticmethod
    def _finished_since(
        connection: Connection, stage: str, param_hash: str, card_ids: list[int], seen: dict[int, ResultFingerprint]
    ) -> set[int]:
        from core.models import StageResult

        if not card_ids:
            return set()
        now = {
            card_id: (status, started)
            for card_id, status, started in connection.execute(
                select(StageResult.card_id, StageResult.status, StageResult.started_at).where(
                    StageResult.stage == stage, StageResult.param_hash == param_hash, StageResult.card_id.in_(card_ids)
                )
            )
        }
        return {card_id for card_id in card_ids if now.get(card_id) != seen.get(card_id)}


def result_fingerprint(status: str | None, started_at: Any) -> ResultFingerprint:
    return None if status is None else (status, started_at)
