"""What staff say about batches and invite links: a batch's name and state (open, paused, closed),
an invite link's expiry and revocation.

Kept as audit events (no card, ``entity`` :data:`BATCH_ENTITY` or :data:`INVITE_ENTITY`,
``entity_id`` the batch or worker id), not as columns: the schema's next migration number is
someone else's, and an audit event is the record of who changed what anyway. The latest event
of a kind wins. Reads filter on ``card_id IS NULL`` first, which the ``card_id`` index serves:
events about no card (batch creations, releases, collection-wide orientation words, these) are a
small part of the trail, which is mostly per-card decisions.

A paused batch gives no new tasks (holds already handed out can still be answered) and can be
resumed; a closed batch gives no new tasks, cannot be reopened, and its cards count as in no
batch for the next one (:func:`annotation.batches.cards_in_open_batches`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, func, select

from core.audit import AuditEvent, record_event
from core.db import db, utcnow
from core.models import Person

from .models import Batch, CrowdSession, Worker
from .sessions import complete_session
from .task_errors import TaskError

BATCH_ENTITY = "crowd_batch_label"
INVITE_ENTITY = "crowd_invite"
BATCH_STATES: tuple[str, ...] = ("open", "paused", "closed")
# The state event's action for each state a curator can put a batch in.
STATE_ACTIONS = {"paused": "pause", "open": "resume", "closed": "close"}
NO_NEW_TASKS_ACTIONS: tuple[str, ...] = ("pause", "close")
MAX_BATCH_NAME = 120
DEFAULT_INVITE_DAYS = 30
MAX_INVITE_DAYS = 365


def _utc(moment: datetime) -> datetime:
    # SQLite hands back naive datetimes for DateTime(timezone=True); they were stored as UTC.
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


def _latest_state_action(batch_id: Any) -> Any:
    """SQL: the latest pause/resume/close action for ``batch_id`` (a column or a value), or NULL."""
    return (
        select(AuditEvent.action)
        .where(
            AuditEvent.card_id.is_(None),
            AuditEvent.entity == BATCH_ENTITY,
            AuditEvent.entity_id == batch_id,
            AuditEvent.action.in_(tuple(STATE_ACTIONS.values())),
        )
        .order_by(AuditEvent.id.desc())
        .limit(1)
        .scalar_subquery()
    )


def batch_takes_new_tasks() -> ColumnElement[bool]:
    """SQL, correlated to :class:`Batch`: the batch is neither paused nor closed."""
    return func.coalesce(_latest_state_action(Batch.id), "resume").not_in(NO_NEW_TASKS_ACTIONS)


def batch_not_closed() -> ColumnElement[bool]:
    return func.coalesce(_latest_state_action(Batch.id), "resume") != "close"


@dataclass(frozen=True)
class BatchLabel:
    name: str
    state: str  # one of BATCH_STATES


def batch_labels(batch_ids: Iterable[int]) -> dict[int, BatchLabel]:
    """Each batch's name ('' when unnamed) and state; a batch nobody labelled is open and unnamed."""
    ids = sorted(set(batch_ids))
    names: dict[int, str] = {}
    states: dict[int, str] = {}
    by_action = {action: state for state, action in STATE_ACTIONS.items()}
    for start in range(0, len(ids), 500):
        rows = db.session.execute(
            select(AuditEvent.entity_id, AuditEvent.action, AuditEvent.after)
            .where(
                AuditEvent.card_id.is_(None),
                AuditEvent.entity == BATCH_ENTITY,
                AuditEvent.entity_id.in_(ids[start : start + 500]),
            )
            .order_by(AuditEvent.id)
        )
        for batch_id, action, after in rows:
            if action == "name":
                names[batch_id] = str((after or {}).get("name") or "")
            elif action in by_action:
                states[batch_id] = by_action[action]
    return {b: BatchLabel(names.get(b, ""), states.get(b, "open")) for b in ids}


def clean_batch_name(name: str) -> str:
    """A batch name as stored: one line of at most :data:`MAX_BATCH_NAME` characters (may be empty)."""
    name = " ".join(name.split())
    if len(name) > MAX_BATCH_NAME:
        raise TaskError(f"Expected a batch name of at most {MAX_BATCH_NAME} characters, got {len(name)}")
    return name


def name_batch(batch_id: int, name: str, actor: Person | None) -> str:
    """Give a batch a name (an empty one clears it); commits. Returns the name stored."""
    batch = db.session.get(Batch, batch_id)
    if batch is None:
        raise TaskError(f"No batch {batch_id}", 404)
    name = clean_batch_name(name)
    before = batch_labels([batch_id])[batch_id]
    record_event(
        entity=BATCH_ENTITY,
        action="name",
        entity_id=batch_id,
        actor=actor,
        actor_label="web",
        before={"name": before.name},
        after={"name": name},
        why=f"batch {batch_id} named on the batches page",
    )
    db.session.commit()
    return name


def set_batch_state(batch_id: int, state: str, actor: Person | None) -> BatchLabel:
    """Pause, resume or close a batch; commits. A closed batch stays closed (409)."""
    if state not in STATE_ACTIONS:
        raise TaskError(f"Expected a batch state {', '.join(BATCH_STATES)}, got {state[:20]!r}")
    batch = db.session.get(Batch, batch_id)
    if batch is None:
        raise TaskError(f"No batch {batch_id}", 404)
    before = batch_labels([batch_id])[batch_id]
    if before.state == "closed":
        raise TaskError(f"Batch {batch_id} is closed: it cannot be changed again. Make a new batch instead.", 409)
    if before.state == state:
        raise TaskError(f"Batch {batch_id} is already {state}", 409)
    record_event(
        entity=BATCH_ENTITY,
        action=STATE_ACTIONS[state],
        entity_id=batch_id,
        actor=actor,
        actor_label="web",
        before={"state": before.state},
        after={"state": state},
        why=f"batch {batch_id} {state} on the batches page",
    )
    db.session.commit()
    return BatchLabel(before.name, state)


# ----------------------------------------------------------------------------- invite links


@dataclass(frozen=True)
class InviteStatus:
    expires_at: datetime | None  # None: never (invites made before links expired, or the CLI's)
    revoked_at: datetime | None

    def refusal(self, now: datetime | None = None) -> str | None:
        """Why the link no longer works, in words for the annotator; None while it does."""
        if self.revoked_at is not None:
            return (
                "This invite link was withdrawn by the project's staff. If you think that is a mistake, ask them for a new one."
            )
        if self.expires_at is not None and self.expires_at <= (now or utcnow()):
            return (
                f"This invite link expired on {self.expires_at:%Y-%m-%d}. Your answers are saved; "
                "ask the project's staff for a new link to go on."
            )
        return None

    def state(self, now: datetime | None = None) -> str:
        if self.revoked_at is not None:
            return "revoked"
        if self.expires_at is not None and self.expires_at <= (now or utcnow()):
            return "expired"
        return "active"


def invite_statuses(worker_ids: Iterable[int]) -> dict[int, InviteStatus]:
    """Each invited worker's link: when it expires and whether it was revoked."""
    ids = sorted(set(worker_ids))
    expires: dict[int, datetime | None] = {}
    revoked: dict[int, datetime] = {}
    for start in range(0, len(ids), 500):
        rows = db.session.execute(
            select(AuditEvent.entity_id, AuditEvent.action, AuditEvent.after, AuditEvent.at)
            .where(
                AuditEvent.card_id.is_(None),
                AuditEvent.entity == INVITE_ENTITY,
                AuditEvent.entity_id.in_(ids[start : start + 500]),
            )
            .order_by(AuditEvent.id)
        )
        for worker_id, action, after, at in rows:
            if action == "create":
                raw = (after or {}).get("expires_at")
                expires[worker_id] = _utc(datetime.fromisoformat(raw)) if isinstance(raw, str) else None
            elif action == "revoke":
                revoked[worker_id] = _utc(at)
    return {w: InviteStatus(expires.get(w), revoked.get(w)) for w in ids}


def record_invite(worker: Worker, days: int, actor: Person | None) -> datetime:
    """Record when a new invite link expires (``days`` from now); commits."""
    if not 1 <= days <= MAX_INVITE_DAYS:
        raise TaskError(f"Expected an invite to last 1 to {MAX_INVITE_DAYS} days, got {days}")
    expires_at = utcnow() + timedelta(days=days)
    record_event(
        entity=INVITE_ENTITY,
        action="create",
        entity_id=worker.id,
        actor=actor,
        actor_label="web",
        after={"name": worker.external_id, "expires_at": expires_at.isoformat()},
        why=f"invite link for {worker.external_id}, {days} days",
    )
    db.session.commit()
    return expires_at


def revoke_invite(worker_id: int, actor: Person | None) -> Worker:
    """Withdraw an invite link: the link refuses with a page saying so, and the sessions it opened
    end now (their task pages take no more answers; their holds go back to the pool). Commits."""
    worker = db.session.get(Worker, worker_id)
    if worker is None or worker.provider != "invite":
        raise TaskError(f"No invited annotator {worker_id}", 404)
    if invite_statuses([worker_id])[worker_id].revoked_at is not None:
        raise TaskError(f"The invite link of {worker.external_id} is already revoked", 409)
    record_event(
        entity=INVITE_ENTITY,
        action="revoke",
        entity_id=worker_id,
        actor=actor,
        actor_label="web",
        before={"name": worker.external_id},
        why=f"invite link of {worker.external_id} revoked on the batches page",
    )
    db.session.commit()
    open_sessions = list(
        db.session.scalars(
            select(CrowdSession.id).where(CrowdSession.worker_id == worker_id, CrowdSession.completed_at.is_(None))
        )
    )
    for session_id in open_sessions:
        complete_session(session_id)
    return worker
