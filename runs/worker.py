"""The background worker: recompute pending and stale work as people's decisions arrive.

The loop between the machine and people closes here. A curator changes a card's eye order, a
dispute is settled, the crowd's crop boxes arrive: the card's results are stale or its next
stage is due (:mod:`runs.card_state`), and the worker runs the default stages again over the
catalogue, which recomputes exactly those cards (the planner, :func:`runs.planning.pending_cards`,
redoes a result whose inputs changed and leaves the rest). A recomputed grade returns the card
to the review queue (review's sync after each grade write).

- **When it runs a round**: at start, whenever the *change mark* moves (people's decisions, new
  cards: :func:`change_mark`, one cheap query per poll), and at least every ``full_every_s``
  seconds anyway (a card whose stage failed for a reason that has since gone away). An idle
  worker costs one small query per ``poll_s``.
- **No work done twice**: it computes through the catalogue's claims (:mod:`runs.claims`) like
  ``keystone run``, with ``--no-wait``: a card another run holds is left to it.
- **Seen from the pages**: each worker keeps a :class:`PipelineWorker` row that it beats every
  poll; :func:`live_workers` are those that beat within :data:`ALIVE_S`, and the card pages say
  "the background worker recomputes it shortly" only while one is alive.
- **Started by** ``keystone serve`` (and ``keystone demo``) in a child process, whatever the
  server, unless ``--no-worker``; on its own by ``keystone worker``. A worker started by a
  server exits when that server is gone (``parent_pid``), even if the server was killed.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import DateTime, Integer, String, delete, func, select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Mapped, mapped_column

from core.db import JSONType, db, utcnow
from core.models import Card

log = logging.getLogger(__name__)

DEFAULT_POLL_S = 5.0
DEFAULT_FULL_EVERY_S = 600.0
# A worker that has not beaten for this long is taken for dead (it beats every poll, and a round
# beats from the claims heartbeat thread too).
ALIVE_S = 90.0
# How often a worker started by a server checks that the server is still there.
PARENT_CHECK_S = 2.0


class PipelineWorker(db.Model):
    """One running background worker (``keystone worker``), as the pages see it."""

    __tablename__ = "pipeline_workers"

    id: Mapped[str] = mapped_column(String(120), primary_key=True)  # its claims driver id
    host: Mapped[str] = mapped_column(String(200))
    pid: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    beat_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    state: Mapped[str] = mapped_column(String(20))  # idle | computing
    rounds: Mapped[int] = mapped_column(Integer, default=0)
    last_round: Mapped[dict[str, Any] | None] = mapped_column(JSONType)


def live_workers(alive_s: float = ALIVE_S) -> list[PipelineWorker]:
    """The workers that beat within ``alive_s`` seconds, newest beat first."""
    since = utcnow() - timedelta(seconds=alive_s)
    return list(
        db.session.scalars(select(PipelineWorker).where(PipelineWorker.beat_at >= since).order_by(PipelineWorker.beat_at.desc()))
    )


def change_mark() -> tuple[Any, ...]:
    """What moves when people decide something or cards arrive: the newest audit event not
    written by the pipeline itself (curators' overrides, rulings, reviews, operators' words,
    fits), the newest card, and whatever the features register (the crowd's aggregates:
    ``core.hooks.StageHooks.change_marks``). One query each."""
    from core.audit import AuditEvent
    from core.hooks import stage_hooks

    # Each a lookup at the end of an index, whatever the catalogue's size: no count (a count of
    # 250,000 cards scans them every poll), and one max() per SELECT (SQLite's shortcut).
    people = db.session.scalar(
        select(AuditEvent.id).where(AuditEvent.actor != "pipeline").order_by(AuditEvent.id.desc()).limit(1)
    )
    cards = db.session.scalar(select(func.max(Card.id)))
    marks = [mark() for mark in stage_hooks().change_marks]
    db.session.commit()  # end the read transaction: an idle worker holds no snapshot
    return (people, cards, *marks)


@dataclass
class WorkerRound:
    """What one round did: the stages it ran and what each computed."""

    trigger: str  # start | decisions | periodic | once
    started_at: datetime
    seconds: float = 0.0
    stages: list[dict[str, Any]] = field(default_factory=list)

    @property
    def computed(self) -> int:
        return sum(stage["processed"] for stage in self.stages)

    @property
    def failed(self) -> int:
        return sum(stage["failed"] for stage in self.stages)

    def as_json(self) -> dict[str, Any]:
        return {
            "trigger": self.trigger,
            "started_at": self.started_at.isoformat(),
            "seconds": round(self.seconds, 3),
            "computed": self.computed,
            "failed": self.failed,
            "stages": self.stages,
        }


def optional_stages_to_refresh(stage_names: Sequence[str]) -> dict[str, set[int]]:
    """The stages ``keystone run`` runs only when named (views) that some cards already have,
    with the cards that have none: a round keeps the optional results an operator chose to
    compute up to date (a stale view is recomputed), and computes none for the other cards."""
    from core.models import StageResult
    from pipeline.stages.spec import declared_stages

    leave_out: dict[str, set[int]] = {}
    for name, declaration in declared_stages().items():
        if declaration.keystone_run != "on_request" or name in stage_names:
            continue
        having = set(db.session.scalars(select(StageResult.card_id).where(StageResult.stage == name).distinct()))
        if having:
            leave_out[name] = set(db.session.scalars(select(Card.id))) - having
    db.session.commit()
    return leave_out


def run_round(
    trigger: str, stage_names: Sequence[str], executor: Any, driver: Any, data_dir: Path, refresh_optional: bool = True
) -> WorkerRound:
    """Run ``stage_names`` once over the catalogue, chained, leaving cards another run holds;
    with ``refresh_optional``, then the optional stages some cards have, on those cards
    (:func:`optional_stages_to_refresh`)."""
    from runs.loop import run_stage, run_stages
    from runs.specs import available_stages

    began = time.monotonic()
    report = WorkerRound(trigger, utcnow())
    specs = available_stages()  # per round: a grade model fitted meanwhile is used
    optional = optional_stages_to_refresh(stage_names) if refresh_optional else {}

    def run_one(spec: Any, followers: Any, leave_out: Any) -> Any:
        # an optional stage leaves out the cards that never had it
        leave_out = {**leave_out, spec.name: set(leave_out.get(spec.name, ())) | optional.get(spec.name, set())}
        return run_stage(
            spec,
            data_dir=data_dir,
            executor=executor,
            driver=driver,
            wait_for_held=False,
            followers=followers,
            leave_out=leave_out,
        )

    # The optional stages after the others and unchained: a chain would take every card the round
    # rectifies on into them, those that never had them too.
    reports = list(run_stages([specs[name] for name in stage_names], run_one, chain=True))
    reports += run_stages([specs[name] for name in optional if name in specs], run_one, chain=False)
    for stage_report in reports:
        report.stages.append(
            {
                "stage": stage_report.stage,
                "processed": stage_report.processed,
                "failed": stage_report.failed,
                "outcomes": dict(stage_report.outcomes),
                "held_by_other_run": stage_report.held_by_other_run,
                "seconds": round(stage_report.seconds, 3),
            }
        )
    report.seconds = time.monotonic() - began
    return report


class BackgroundWorker:
    """The worker loop over one claims driver and one executor (see the module docstring)."""

    def __init__(
        self,
        stage_names: Sequence[str],
        executor: Any,
        driver: Any,
        data_dir: Path,
        *,
        poll_s: float = DEFAULT_POLL_S,
        full_every_s: float = DEFAULT_FULL_EVERY_S,
        parent_pid: int | None = None,
        on_round: Callable[[WorkerRound], None] | None = None,
        refresh_optional: bool = True,
    ) -> None:
        self.stage_names = list(stage_names)
        self.executor = executor
        self.driver = driver
        self.data_dir = data_dir
        self.poll_s = poll_s
        self.full_every_s = full_every_s
        self.parent_pid = parent_pid
        self.on_round = on_round
        self.refresh_optional = refresh_optional
        self.rounds: list[WorkerRound] = []
        self.failures: list[str] = []  # rounds that raised, in words (the worker went on)
        self.stop = threading.Event()

    @contextmanager
    def registered(self) -> Iterator[BackgroundWorker]:
        """Keep this worker's row while it runs; remove it on the way out."""
        now = utcnow()
        db.session.merge(
            PipelineWorker(
                id=self.driver.id,
                host=socket.gethostname()[:200],
                pid=os.getpid(),
                started_at=now,
                beat_at=now,
                state="idle",
                rounds=0,
            )
        )
        db.session.commit()
        try:
            yield self
        finally:
            # A stop (SIGTERM -> SystemExit) can land in the middle of a commit, which leaves the
            # session unusable ("in 'committed' state"): drop it and remove the row from a fresh one.
            try:
                db.session.rollback()
            except SQLAlchemyError:
                pass
            db.session.remove()
            try:
                db.session.execute(delete(PipelineWorker).where(PipelineWorker.id == self.driver.id))
                db.session.commit()
            except SQLAlchemyError as exc:  # it is taken for dead after ALIVE_S anyway
                log.warning("could not remove worker row %s: %s", self.driver.id, exc)

    def beat(self, state: str, last: WorkerRound | None = None) -> None:
        try:
            self._beat(state, last)
        except SQLAlchemyError as exc:  # a busy database: the next poll beats again
            db.session.rollback()
            log.warning("worker %s could not beat: %s", self.driver.id, exc)

    def _beat(self, state: str, last: WorkerRound | None) -> None:
        row = db.session.get(PipelineWorker, self.driver.id)
        if row is None:  # removed by hand (or by a test): come back
            row = PipelineWorker(
                id=self.driver.id, host=socket.gethostname()[:200], pid=os.getpid(), started_at=utcnow(), rounds=0
            )
            db.session.add(row)
        row.beat_at, row.state = utcnow(), state
        if last is not None:
            row.rounds = len(self.rounds)
            row.last_round = last.as_json()
        db.session.commit()

    def parent_gone(self) -> bool:
        return self.parent_pid is not None and os.getppid() != self.parent_pid

    def run(self, once: bool = False) -> list[WorkerRound]:
        """Run rounds until stopped (``once``: one round, then return)."""
        seen: tuple[Any, ...] | None = None
        last_full = 0.0
        with self.registered():
            while not self.stop.is_set() and not self.parent_gone():
                mark = change_mark()
                due_full = time.monotonic() - last_full >= self.full_every_s
                if once or mark != seen or due_full:
                    trigger = "once" if once else "start" if seen is None else "decisions" if mark != seen else "periodic"
                    # The mark read *before* the round: a decision made during it starts another.
                    seen = mark
                    self.beat("computing")
                    try:
                        done = run_round(
                            trigger, self.stage_names, self.executor, self.driver, self.data_dir, self.refresh_optional
                        )
                    except Exception as exc:  # a database that went away, a full disk: try again next poll
                        if once:
                            raise
                        db.session.rollback()
                        log.exception("worker round failed; retrying after %s s", self.poll_s)
                        self.failures.append(f"{type(exc).__name__}: {exc}")
                        seen = None  # the decisions it missed are still to do
                        self._sleep()
                        continue
                    last_full = time.monotonic()
                    self.rounds.append(done)
                    self.beat("idle", done)
                    if self.on_round is not None:
                        self.on_round(done)
                    if once:
                        break
                else:
                    self.beat("idle")
                self._sleep()
        return self.rounds

    def _sleep(self) -> None:
        deadline = time.monotonic() + self.poll_s
        while not self.stop.is_set() and not self.parent_gone():
            left = deadline - time.monotonic()
            if left <= 0:
                return
            self.stop.wait(min(left, PARENT_CHECK_S))


# ----------------------------------------------------------------------------- a server's worker


def worker_command_line(parent_pid: int) -> list[str]:
    """How a server starts its worker: this interpreter, the same CLI, one inline worker process
    (the server's processes keep the other cores)."""
    return [sys.executable, "-m", "app", "worker", "--parent-pid", str(parent_pid)]


def start_server_worker(env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
    """Start a ``keystone worker`` beside a server; it exits when this process does."""
    return subprocess.Popen(worker_command_line(os.getpid()), env=env or dict(os.environ))


def stop_server_worker(process: subprocess.Popen[bytes], timeout_s: float = 30.0) -> None:
    """Ask the worker to stop (SIGTERM finishes the card batch in hand and releases its claims)."""
    if process.poll() is not None:
        return
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
