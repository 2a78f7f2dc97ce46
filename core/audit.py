"""The audit trail: one append-only row per change people or the pipeline make to what others rely on.

Every change to a grade, a decision, a crowd annotation, an orientation, a release or a person
(the admin's changes) is written to :class:`AuditEvent` in the same transaction as the change.
The trail is append-only: the ORM refuses updates and deletes (:class:`AuditTamperError`), and
the migration adds database triggers that refuse them too, so a trace survives a bug or a
hand-written SQL statement. It lives in the kernel because features at every level write to it
(``core.people``, ``review``, ``exports``); its table, ``audit_events``, is unchanged.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import DateTime, ForeignKey, Integer, String, Text, event
from sqlalchemy.orm import Mapped, Session, mapped_column

from core.db import JSONType, db, utcnow
from core.models import Person


class AuditEvent(db.Model):
    """One change: who, when, to what, before, after and why. Never updated, never deleted."""

    __tablename__ = "audit_events"

    id: Mapped[int] = mapped_column(primary_key=True)
    card_id: Mapped[int | None] = mapped_column(ForeignKey("cards.id"), index=True)
    entity: Mapped[str] = mapped_column(String(30))  # review | grade | aggregate | gold | release
    entity_id: Mapped[int | None] = mapped_column(Integer)
    action: Mapped[str] = mapped_column(String(40))
    actor_id: Mapped[int | None] = mapped_column(ForeignKey("people.id"))
    actor: Mapped[str] = mapped_column(String(200))  # username, or "pipeline" / "crowd"
    at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, index=True)
    before: Mapped[dict[str, Any] | None] = mapped_column(JSONType)
    after: Mapped[dict[str, Any] | None] = mapped_column(JSONType)
    why: Mapped[str] = mapped_column(Text, default="")


class AuditTamperError(RuntimeError):
    """Raised when code tries to change or delete an audit event."""


@event.listens_for(Session, "before_flush")
def _refuse_audit_changes(session: Session, _context: Any, _instances: Any) -> None:
    for instance in (*session.dirty, *session.deleted):
        if isinstance(instance, AuditEvent) and (instance in session.deleted or session.is_modified(instance)):
            raise AuditTamperError(f"audit event {instance.id} is append-only: it cannot be changed or deleted")


def record_event(
    *,
    entity: str,
    action: str,
    card_id: int | None = None,
    entity_id: int | None = None,
    actor: Person | None = None,
    actor_label: str | None = None,
    before: dict[str, Any] | None = None,
    after: dict[str, Any] | None = None,
    why: str = "",
) -> AuditEvent:
    """Add an audit event to the current session (committed with the change it describes)."""
    event_row = AuditEvent(
        card_id=card_id,
        entity=entity,
        entity_id=entity_id,
        action=action,
        actor_id=actor.id if actor is not None else None,
        actor=actor.username if actor is not None else (actor_label or "system"),
        before=before,
        after=after,
        why=why or "",
    )
    db.session.add(event_row)
    return event_row
