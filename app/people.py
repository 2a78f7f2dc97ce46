"""``keystone users``: create people with roles and list them (the web page is /auth/people)."""

from __future__ import annotations

import click
from flask.cli import with_appcontext
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from .db import db
from .models import ROLES, Person


def create_person(username: str, password: str | None, roles: list[str], display_name: str = "") -> Person:
    person = Person(username=username, display_name=display_name or username)
    if password:
        person.set_password(password)
    for role in roles:
        person.grant(role)
    db.session.add(person)
    db.session.commit()
    return person


@click.group("users")
def users_group() -> None:
    """Manage people and their roles (annotator, curator, exporter, admin)."""


@users_group.command("add")
@click.argument("username")
@click.option("--role", "roles", multiple=True, required=True, type=click.Choice(ROLES), help="Repeatable.")
@click.option("--password", prompt=True, hide_input=True, confirmation_prompt=True,
              help="Prompted for when not given.")
@click.option("--name", "display_name", default="", help="Display name.")
@with_appcontext
def add_user(username: str, roles: tuple[str, ...], password: str, display_name: str) -> None:
    """Add a person who logs in with USERNAME and a password."""
    from .console import ensure_database

    ensure_database()
    if len(password) < 8:
        raise click.BadParameter("use at least 8 characters", param_hint="--password")
    try:
        person = create_person(username, password, list(roles), display_name)
    except IntegrityError as exc:
        db.session.rollback()
        raise click.ClickException(f"a person called {username!r} already exists") from exc
    click.echo(f"added {person.username} ({', '.join(sorted(person.roles))})")


@users_group.command("list")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
@with_appcontext
def list_users(as_json: bool) -> None:
    """List people and their roles."""
    from .console import emit_json, ensure_database

    ensure_database()
    people = list(db.session.scalars(select(Person).order_by(Person.username)))
    rows = [{"id": p.id, "username": p.username, "roles": sorted(p.roles), "active": p.active} for p in people]
    if as_json:
        emit_json({"people": rows})
        return
    for row in rows:
        click.echo(f"{row['username']:<24} {', '.join(row['roles'])}{'' if row['active'] else '  (inactive)'}")
