"""The admin's people page: deactivate and reactivate, reset a password (one-time or typed),
change roles; each change in the audit trail; an admin cannot lock the app out of admins."""

from __future__ import annotations

import re

import pytest
from sqlalchemy import select


def _person_id(app, username: str) -> int:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Person

    with app.app_context():
        return db.session.scalar(select(Person.id).where(Person.username == username))


def _trail(app, person_id: int) -> list[tuple[str, str, dict, dict]]:  # type: ignore[no-untyped-def]
    from core.audit import AuditEvent
    from core.db import db

    with app.app_context():
        return [
            (e.action, e.actor, e.before, e.after)
            for e in db.session.scalars(
                select(AuditEvent).where(AuditEvent.entity == "person", AuditEvent.entity_id == person_id).order_by(AuditEvent.id)
            )
        ]


def _log_in(app, password: str, username: str) -> int:  # type: ignore[no-untyped-def]
    other = app.test_client()
    page = other.get("/auth/login").get_data(as_text=True)
    token = re.search(r'name="csrf_token"[^>]*value="([^"]+)"', page).group(1)
    return other.post("/auth/login", data={"username": username, "password": password, "csrf_token": token}).status_code


def test_deactivate_then_reactivate_with_the_audit_trail(app, client, login, make_person, csrf_token) -> None:
    admin = login("admin")
    annotator = make_person("annotator")
    target = _person_id(app, annotator.username)
    token = csrf_token("/auth/people")
    assert _log_in(app, annotator.password, annotator.username) == 302
    done = client.post(f"/auth/people/{target}/active", data={"csrf_token": token, "active": "0"})
    assert done.status_code == 303
    page = client.get("/auth/people").get_data(as_text=True)
    assert "is deactivated" in page and "deactivated" in page
    assert _log_in(app, annotator.password, annotator.username) == 403
    again = client.post(f"/auth/people/{target}/active", data={"csrf_token": token, "active": "0"})
    assert again.status_code == 409 and "already deactivated" in again.get_data(as_text=True)
    assert client.post(f"/auth/people/{target}/active", data={"csrf_token": token, "active": "1"}).status_code == 303
    assert _log_in(app, annotator.password, annotator.username) == 302
    trail = _trail(app, target)
    assert [(action, actor) for action, actor, _, _ in trail] == [
        ("deactivated", admin.username),
        ("reactivated", admin.username),
    ]
    assert trail[0][2]["active"] is True and trail[0][3]["active"] is False


def test_one_time_and_typed_passwords(app, client, login, make_person, csrf_token) -> None:
    login("admin")
    curator = make_person("curator")
    target = _person_id(app, curator.username)
    token = csrf_token("/auth/people")
    shown = client.post(f"/auth/people/{target}/password", data={"csrf_token": token})
    html = shown.get_data(as_text=True)
    assert shown.status_code == 200 and shown.headers["Cache-Control"] == "no-store"
    one_time = re.search(r'<code class="one-time">([^<]+)</code>', html).group(1)
    assert len(one_time) >= 16
    assert _log_in(app, curator.password, curator.username) == 200  # the old password no longer works
    assert _log_in(app, one_time, curator.username) == 302
    assert one_time not in client.get("/auth/people").get_data(as_text=True)  # shown once

    short = client.post(f"/auth/people/{target}/password", data={"csrf_token": token, "password": "short"})
    assert short.status_code == 400 and "at least 8 characters" in short.get_data(as_text=True)
    typed = client.post(f"/auth/people/{target}/password", data={"csrf_token": token, "password": "a-new-secret"})
    assert typed.status_code == 303 and _log_in(app, "a-new-secret", curator.username) == 302
    assert [action for action, *_ in _trail(app, target)] == ["password_reset", "password_reset"]


def test_roles_change_and_bad_input(app, client, login, make_person, csrf_token) -> None:
    login("admin")
    person = make_person("annotator")
    target = _person_id(app, person.username)
    token = csrf_token("/auth/people")
    changed = client.post(f"/auth/people/{target}/roles", data={"csrf_token": token, "roles": ["curator", "exporter"]})
    assert changed.status_code == 303
    action, _, before, after = _trail(app, target)[-1]
    assert action == "roles_changed" and before["roles"] == ["annotator"] and after["roles"] == ["curator", "exporter"]
    for data, status in [({"roles": []}, 400), ({"roles": ["wizard"]}, 400), ({"roles": ["curator", "exporter"]}, 409)]:
        response = client.post(f"/auth/people/{target}/roles", data={"csrf_token": token, **data})
        assert response.status_code == status
    assert client.post("/auth/people/99999/roles", data={"csrf_token": token, "roles": ["curator"]}).status_code == 404
    assert client.post(f"/auth/people/{target}/active", data={"csrf_token": token, "active": "maybe"}).status_code == 400
    assert client.post(f"/auth/people/{target}/active", data={"active": "0"}).status_code == 400  # no CSRF token


def test_an_admin_cannot_leave_the_app_without_an_admin(app, client, login, make_person, csrf_token) -> None:
    admin = login("admin")
    me = _person_id(app, admin.username)
    token = csrf_token("/auth/people")
    myself = client.post(f"/auth/people/{me}/active", data={"csrf_token": token, "active": "0"})
    assert myself.status_code == 409 and "cannot deactivate yourself" in myself.get_data(as_text=True)
    demote = client.post(f"/auth/people/{me}/roles", data={"csrf_token": token, "roles": ["curator"]})
    assert demote.status_code == 409 and "only active admin" in demote.get_data(as_text=True)
    make_person("admin")  # with a second admin, demoting oneself is allowed
    assert client.post(f"/auth/people/{me}/roles", data={"csrf_token": token, "roles": ["curator"]}).status_code == 303
    assert client.get("/auth/people").status_code == 403  # and takes effect at once


@pytest.mark.parametrize("role", ["curator", "exporter", "annotator"])
def test_only_admins_manage_people(client, login, make_person, app, csrf_token, role) -> None:
    other = make_person("annotator")
    login(role)
    token = csrf_token("/")
    target = _person_id(app, other.username)
    for path, data in [("active", {"active": "0"}), ("password", {}), ("roles", {"roles": ["admin"]})]:
        assert client.post(f"/auth/people/{target}/{path}", data={"csrf_token": token, **data}).status_code == 403
