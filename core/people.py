"""People: creating them, and the admin's changes to them (deactivate, reactivate, reset a
password, change roles), plus ``keystone users`` (the web page is /auth/people).

Every admin change is written to the audit trail (``core.audit.AuditEvent``, entity
``person``: who changed whom, before, after) in the same transaction as the change. An admin
cannot deactivate themselves, and no change may leave the app without an active admin.
"""

from __future__ import annotations

import secrets
from typing import Any

import click
from flask.cli import with_appcontext
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from core.db import db
from core.models import ROLES, Person


class PeopleError(Exception):
    """An admin change that cannot be made; ``status`` for the HTTP reply."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.message = message
        self.status = status


def same_username(username: str) -> str | None:
    """The existing username equal to ``username`` ignoring case, if any.

    Compared with Python's ``casefold`` over every person (a few dozen staff accounts; crowd
    workers are not people): the database's unique index on ``lower(username)`` folds only
    A-Z on SQLite, so "ÄDMIN" beside "ädmin" is refused here on either database.
    """
    wanted = username.casefold()
    return next((name for name in db.session.scalars(select(Person.username)) if name.casefold() == wanted), None)


def _taken(username: str, existing: str) -> PeopleError:
    same = "" if existing == username else f" (usernames are the same whatever their case, so {username!r} is taken)"
    return PeopleError(f"A person called {existing!r} already exists{same}.", 409)


def create_person(username: str, password: str | None, roles: list[str], display_name: str = "") -> Person:
    """Add a person; PeopleError (409) when the username is taken, whatever its case."""
    existing = same_username(username)
    if existing is not None:
        db.session.rollback()
        raise _taken(username, existing)
    person = Person(username=username, display_name=display_name or username)
    if password:
        person.set_password(password)
    for role in roles:
        person.grant(role)
    db.session.add(person)
    try:
        db.session.commit()
    except IntegrityError:
        # Someone added the same name (or a case-variant) between the check and the commit.
        db.session.rollback()
        raise _taken(username, same_username(username) or username) from None
    return person


ONE_TIME_PASSWORD_BYTES = 12  # 16 URL-safe characters


def _person_snapshot(person: Person) -> dict[str, Any]:
    return {"active": person.active, "roles": sorted(person.roles), "has_password": person.password_hash is not None}


def _get_person(person_id: int) -> Person:
    person = db.session.get(Person, person_id, populate_existing=True)
    if person is None:
        db.session.rollback()
        raise PeopleError(f"There is no person {person_id}", 404)
    return person


def _other_active_admins(person_id: int) -> int:
    return sum(
        1
        for other in db.session.scalars(select(Person).where(Person.active.is_(True), Person.id != person_id))
        if "admin" in other.roles
    )


def _record(actor: Person, person: Person, action: str, before: dict[str, Any], why: str) -> None:
    from core.audit import record_event

    record_event(
        entity="person", action=action, entity_id=person.id, actor=actor, before=before, after=_person_snapshot(person), why=why
    )


def set_active(person_id: int, active: bool, *, actor: Person) -> Person:
    """Deactivate (ends their sessions, refuses their logins) or reactivate a person."""
    person = _get_person(person_id)
    if person.active == active:
        db.session.rollback()
        raise PeopleError(f"{person.username} is already {'active' if active else 'deactivated'}", 409)
    if not active and person.id == actor.id:
        db.session.rollback()
        raise PeopleError("You cannot deactivate yourself: ask another admin", 409)
    if not active and "admin" in person.roles and _other_active_admins(person.id) == 0:
        db.session.rollback()
        raise PeopleError(f"{person.username} is the only active admin: make someone else an admin first", 409)
    before = _person_snapshot(person)
    person.active = active
    db.session.flush()
    _record(
        actor,
        person,
        "reactivated" if active else "deactivated",
        before,
        f"{actor.username} {'reactivated' if active else 'deactivated'} {person.username}",
    )
    db.session.commit()
    return person


def reset_password(
    person_id: int, *, actor: Person, password: str | None = None, min_length: int = 8
) -> tuple[Person, str | None]:
    """Set a new password (the admin's, or a generated one returned once to be shown and never
    stored in clear); the person's sessions end. Returns (person, the generated password or None)."""
    if password is not None and len(password) < min_length:
        raise PeopleError(f"Use at least {min_length} characters for the new password")
    person = _get_person(person_id)
    generated = secrets.token_urlsafe(ONE_TIME_PASSWORD_BYTES) if password is None else None
    before = _person_snapshot(person)
    person.set_password(password if password is not None else generated or "")
    db.session.flush()
    _record(
        actor,
        person,
        "password_reset",
        before,
        f"{actor.username} {'generated a one-time password for' if generated else 'set a new password for'} {person.username}",
    )
    db.session.commit()
    return person, generated


def set_roles(person_id: int, roles: list[str], *, actor: Person) -> Person:
    """Replace a person's roles; nobody may be left with none, and the last admin keeps admin."""
    wanted = sorted(set(roles))
    unknown = [role for role in wanted if role not in ROLES]
    if unknown:
        raise PeopleError(f"Unknown role {', '.join(unknown)}; expected some of {', '.join(ROLES)}")
    if not wanted:
        raise PeopleError("Choose at least one role (deactivate the person to take all access away)")
    person = _get_person(person_id)
    if sorted(person.roles) == wanted:
        db.session.rollback()
        raise PeopleError(f"{person.username} already has exactly these roles", 409)
    if "admin" in person.roles and "admin" not in wanted and person.active and _other_active_admins(person.id) == 0:
        db.session.rollback()
        who = "you are" if person.id == actor.id else f"{person.username} is"
        raise PeopleError(f"{who[0].upper() + who[1:]} the only active admin: make someone else an admin first", 409)
    before = _person_snapshot(person)
    for row in list(person.role_rows):
        if row.role not in wanted:
            person.role_rows.remove(row)
    for role in wanted:
        person.grant(role)
    db.session.flush()
    _record(
        actor,
        person,
        "roles_changed",
        before,
        f"{actor.username} changed the roles of {person.username}: {', '.join(before['roles']) or 'none'} -> {', '.join(wanted)}",
    )
    db.session.commit()
    return person


def person_history(person_id: int, limit: int = 20) -> list[Any]:
    """The newest admin changes to a person, newest first."""
    from core.audit import AuditEvent

    return list(
        db.session.scalars(
            select(AuditEvent)
            .where(AuditEvent.entity == "person", AuditEvent.entity_id == person_id)
            .order_by(AuditEvent.id.desc())
            .limit(limit)
        )
    )


@click.group("users")
def users_group() -> None:
    """Manage people and their roles (annotator, curator, exporter, admin)."""


@users_group.command("add")
@click.argument("username")
@click.option("--role", "roles", multiple=True, required=True, type=click.Choice(ROLES), help="Repeatable.")
@click.option("--password", prompt=True, hide_input=True, confirmation_prompt=True, help="Prompted for when not given.")
@click.option("--name", "display_name", default="", help="Display name.")
@with_appcontext
def add_user(username: str, roles: tuple[str, ...], password: str, display_name: str) -> None:
    """Add a person who logs in with USERNAME and a password."""
    from core.console import ensure_database

    ensure_database()
    if len(password) < 8:
        raise click.BadParameter("use at least 8 characters", param_hint="--password")
    try:
        person = create_person(username, password, list(roles), display_name)
    except PeopleError as exc:
        raise click.ClickException(exc.message) from exc
    click.echo(f"added {person.username} ({', '.join(sorted(person.roles))})")


@users_group.command("list")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
@with_appcontext
def list_users(as_json: bool) -> None:
    """List people and their roles."""
    from core.console import emit_json, ensure_database

    ensure_database()
    people = list(db.session.scalars(select(Person).order_by(Person.username)))
    rows = [{"id": p.id, "username": p.username, "roles": sorted(p.roles), "active": p.active} for p in people]
    if as_json:
        emit_json({"people": rows})
        return
    for row in rows:
        click.echo(f"{row['username']:<24} {', '.join(row['roles'])}{'' if row['active'] else '  (inactive)'}")
