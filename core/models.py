"""The models everything references: collections, cards, stage results, people and roles.

Feature-specific models live with their feature (``annotation/``, ``review/``, ``exports/``).
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from flask_login import UserMixin
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
    event,
    inspect,
)
from sqlalchemy.orm import Mapped, Session, mapped_column, relationship
from werkzeug.security import check_password_hash, generate_password_hash

from core.db import JSONType, db, utcnow

ROLES: tuple[str, ...] = ("annotator", "curator", "exporter", "admin")
STAGE_STATUSES: tuple[str, ...] = ("done", "skipped", "failed")
# What the append-only sign-in trail records (see AuthEvent).
AUTH_ACTIONS: tuple[str, ...] = ("login", "login_failed", "login_throttled", "logout", "session_refused")
THROTTLE_SCOPES: tuple[str, ...] = ("account", "address")
# A card's current state: where it stands in the flow, derived from its latest stage results.
CARD_STATES: tuple[str, ...] = ("ingested", "pass", "review", "culled", "failed")


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class Collection(db.Model):
    __tablename__ = "collections"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    description: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    cards: Mapped[list[Card]] = relationship(back_populates="collection")


class CollectionOrientation(db.Model):
    """An operator's word on the orientation of every card of a collection, flag by flag: a
    collection known to be prints (``inverted`` false), or known to be scanned in eye order
    (``swapped`` false). Null: not said; the step, the crowd and curators decide that flag card
    by card. One row per collection, replaced by the next word and removed when every flag is
    cleared; a curator's override on one card wins over it (see :mod:`pipeline.decided_orientation`). Every
    change is also an audit event (entity ``orientation``, no card)."""

    __tablename__ = "collection_orientations"

    id: Mapped[int] = mapped_column(primary_key=True)
    collection_id: Mapped[int] = mapped_column(ForeignKey("collections.id", ondelete="CASCADE"), unique=True)
    upside_down: Mapped[bool | None] = mapped_column()
    inverted: Mapped[bool | None] = mapped_column()
    swapped: Mapped[bool | None] = mapped_column()
    # Who said it: an operator's account when named, and always a name to show (the account's
    # username, else the OS user who ran the command).
    set_by_id: Mapped[int | None] = mapped_column(ForeignKey("people.id", ondelete="SET NULL"))
    set_by_name: Mapped[str] = mapped_column(String(200))
    note: Mapped[str] = mapped_column(Text, default="")
    set_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    collection: Mapped[Collection] = relationship()
    set_by: Mapped[Person | None] = relationship()

    @property
    def collection_name(self) -> str:
        return self.collection.name


class Card(db.Model):
    """One scanned stereo card. The original is stored once, by content, and never modified."""

    __tablename__ = "cards"
    __table_args__ = (CheckConstraint(_in("state", CARD_STATES), name="state"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    collection_id: Mapped[int] = mapped_column(ForeignKey("collections.id"), index=True)
    content_hash: Mapped[str] = mapped_column(String(64), unique=True)  # sha256 hex of the bytes
    stored_path: Mapped[str] = mapped_column(String(500))  # relative to KEYSTONE_DATA_DIR
    source_name: Mapped[str] = mapped_column(String(500))  # the ingested file's name
    source_path: Mapped[str] = mapped_column(Text)  # where it was ingested from
    accession: Mapped[str | None] = mapped_column(String(100), index=True)
    width: Mapped[int] = mapped_column(Integer)  # pixels
    height: Mapped[int] = mapped_column(Integer)  # pixels
    image_format: Mapped[str] = mapped_column(String(20))
    byte_size: Mapped[int] = mapped_column(BigInteger)
    source_metadata: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)
    # Set when the card image was made from stereo inputs (an MPO, a left/right pair) or is a
    # side-by-side file with a declared eye order: its originals, hashes, eye order and the check
    # of that order (catalogue.stereo_ingest). NULL for an ordinary scan.
    stereo_source: Mapped[dict[str, Any] | None] = mapped_column(JSONType, nullable=True)
    # Set when the card was ingested from a IIIF canvas (catalogue.iiif_ingest): the canvas id
    # (unique: a canvas is one card however often ingest is retried) and where it came from:
    # manifest, canvas size, Image API service, the size fetched, the rights statement.
    iiif_canvas_id: Mapped[str | None] = mapped_column(String(1000), nullable=True, unique=True, index=True)
    iiif_source: Mapped[dict[str, Any] | None] = mapped_column(JSONType, nullable=True)
    state: Mapped[str] = mapped_column(String(20), default="ingested", index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, onupdate=utcnow)

    collection: Mapped[Collection] = relationship(back_populates="cards")
    stage_results: Mapped[list[StageResult]] = relationship(
        back_populates="card", cascade="all, delete-orphan", order_by="StageResult.id"
    )

    def latest_results(self) -> dict[str, StageResult]:
        """The most recent result per stage (any parameters)."""
        latest: dict[str, StageResult] = {}
        for result in self.stage_results:
            latest[result.stage] = result
        return latest


class StageResult(db.Model):
    """What one stage did to one card with one set of parameters."""

    __tablename__ = "stage_results"
    __table_args__ = (
        UniqueConstraint("card_id", "stage", "param_hash", name="card_stage_params"),
        CheckConstraint(_in("status", STAGE_STATUSES), name="status"),
        Index("ix_stage_results_stage_status", "stage", "status"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    card_id: Mapped[int] = mapped_column(ForeignKey("cards.id", ondelete="CASCADE"), index=True)
    stage: Mapped[str] = mapped_column(String(30))
    param_hash: Mapped[str] = mapped_column(String(32))
    status: Mapped[str] = mapped_column(String(10))
    outcome: Mapped[str | None] = mapped_column(String(30))
    reason: Mapped[str | None] = mapped_column(Text)
    metrics: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)
    artifacts: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)  # name -> path under data dir
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    seconds: Mapped[float | None] = mapped_column(Float)
    code_version: Mapped[str] = mapped_column(String(40), default="")
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    card: Mapped[Card] = relationship(back_populates="stage_results")

    def as_status(self) -> dict[str, Any]:
        return {"status": self.status, "outcome": self.outcome, "reason": self.reason, "metrics": self.metrics}


class MetadataRecord(db.Model):
    """One catalogue row from a metadata CSV, kept whether or not its image has arrived yet."""

    __tablename__ = "metadata_records"
    __table_args__ = (UniqueConstraint("collection_id", "record_key", name="collection_record"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    collection_id: Mapped[int] = mapped_column(ForeignKey("collections.id"), index=True)
    # Normalised key: "accession:<number>" or "file:<lower-case file name>".
    record_key: Mapped[str] = mapped_column(String(600))
    accession: Mapped[str | None] = mapped_column(String(100), index=True)
    file_name: Mapped[str | None] = mapped_column(String(500), index=True)
    fields: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)
    source_file: Mapped[str] = mapped_column(Text)
    row_number: Mapped[int] = mapped_column(Integer)
    card_id: Mapped[int | None] = mapped_column(ForeignKey("cards.id", ondelete="SET NULL"), index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Person(UserMixin, db.Model):
    """Anyone who uses the app. Crowd workers from invite links may have no password."""

    __tablename__ = "people"
    # Unique ignoring case (migration 0013): "ADMIN" cannot be added beside "admin". An
    # expression index, so Alembic's autogenerate leaves it to the migration (app.schema).
    __table_args__ = (Index("uq_people_username_lower", db.text("lower(username)"), unique=True),)

    id: Mapped[int] = mapped_column(primary_key=True)
    username: Mapped[str] = mapped_column(String(120), unique=True)
    display_name: Mapped[str] = mapped_column(String(200), default="")
    password_hash: Mapped[str | None] = mapped_column(String(300))
    active: Mapped[bool] = mapped_column(default=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    # Stored in the session at login; a session carrying an older number is refused. Logging out,
    # a new password and deactivation raise it, which ends every session the person holds.
    session_version: Mapped[int] = mapped_column(Integer, default=1, server_default="1")

    role_rows: Mapped[list[PersonRole]] = relationship(back_populates="person", cascade="all, delete-orphan", lazy="selectin")

    @property
    def roles(self) -> set[str]:
        return {row.role for row in self.role_rows}

    def has_role(self, *roles: str) -> bool:
        # Admins may do everything any other role may.
        return "admin" in self.roles or bool(self.roles.intersection(roles))

    def grant(self, role: str) -> None:
        if role not in ROLES:
            raise ValueError(f"unknown role {role!r}; expected one of {', '.join(ROLES)}")
        if role not in self.roles:
            self.role_rows.append(PersonRole(role=role))

    def set_password(self, password: str) -> None:
        self.password_hash = generate_password_hash(password)

    def check_password(self, password: str) -> bool:
        return self.password_hash is not None and check_password_hash(self.password_hash, password)

    @property
    def is_active(self) -> bool:  # flask-login
        return self.active


@event.listens_for(Person.password_hash, "set")
@event.listens_for(Person.active, "set")
def _end_sessions_on_credential_change(person: Person, value: Any, old_value: Any, _initiator: Any) -> None:
    # Any path that changes a stored person's password or active flag (the CLI, a future admin
    # page, a shell) ends their sessions; a person being created has none to end.
    if inspect(person).has_identity and value != old_value:
        person.session_version = (person.session_version or 0) + 1


class PersonRole(db.Model):
    __tablename__ = "person_roles"
    __table_args__ = (CheckConstraint(_in("role", ROLES), name="role"),)

    person_id: Mapped[int] = mapped_column(ForeignKey("people.id", ondelete="CASCADE"), primary_key=True)
    role: Mapped[str] = mapped_column(String(20), primary_key=True)

    person: Mapped[Person] = relationship(back_populates="role_rows")


class AuthEvent(db.Model):
    """One sign-in event: who (or which name was tried), from where, what happened and why.

    Append-only like ``core.audit.AuditEvent``: the ORM refuses updates and deletes, and the
    migration adds database triggers that refuse them too.
    """

    __tablename__ = "auth_events"
    __table_args__ = (CheckConstraint(_in("action", AUTH_ACTIONS), name="action"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow, index=True)
    action: Mapped[str] = mapped_column(String(30))
    username: Mapped[str] = mapped_column(String(120))  # as typed on the login form, or the person's
    person_id: Mapped[int | None] = mapped_column(ForeignKey("people.id"), index=True)
    address: Mapped[str] = mapped_column(String(64), default="")  # the client's, as throttled
    reason: Mapped[str] = mapped_column(Text, default="")


class AuthEventTamperError(RuntimeError):
    """Raised when code tries to change or delete a sign-in event."""


@event.listens_for(Session, "before_flush")
def _refuse_auth_event_changes(session: Session, _context: Any, _instances: Any) -> None:
    for instance in (*session.dirty, *session.deleted):
        if isinstance(instance, AuthEvent) and (instance in session.deleted or session.is_modified(instance)):
            raise AuthEventTamperError(f"sign-in event {instance.id} is append-only: it cannot be changed or deleted")


class LoginThrottle(db.Model):
    """Failed (and in-flight) password checks against one account or one client address in the
    current window. Kept in the database so every server process counts against one budget."""

    __tablename__ = "login_throttles"
    __table_args__ = (CheckConstraint(_in("scope", THROTTLE_SCOPES), name="scope"),)

    scope: Mapped[str] = mapped_column(String(10), primary_key=True)
    subject: Mapped[str] = mapped_column(String(120), primary_key=True)  # a username or an address
    window_started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    failures: Mapped[int] = mapped_column(Integer, default=0)
