"""Logging in and out, role checks, the admin's people page, CSRF and redirects after login."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select

from core.auth import role_required, safe_next
from core.db import db
from core.models import Person

ROLES = [None, "annotator", "curator", "exporter", "admin"]


def logged_in_as(client) -> str | None:  # type: ignore[no-untyped-def]
    with client.session_transaction() as session:
        return session.get("_user_id")


# --------------------------------------------------------------------------- login


def test_login_page_has_a_csrf_protected_form(client):
    page = client.get("/auth/login")
    assert page.status_code == 200
    html = page.get_data(as_text=True)
    assert 'name="csrf_token"' in html and 'name="username"' in html and 'type="password"' in html


def test_login_with_the_right_password_logs_in_and_goes_to_the_catalogue(client, make_person, csrf_token):
    person = make_person("curator")
    response = client.post(
        "/auth/login", data={"username": person.username, "password": person.password, "csrf_token": csrf_token()}
    )
    assert response.status_code == 302 and response.headers["Location"] == "/"
    assert logged_in_as(client) == str(person.id)
    assert client.get("/").headers["Location"] == "/review/"  # a curator's work starts at the review queue


@pytest.mark.parametrize(
    ("roles", "home"),
    [
        (("curator",), "/review/"),
        (("exporter",), "/releases/"),
        (("admin",), "/cards"),
        (("curator", "exporter"), "/review/"),
        (("annotator",), "/crowd/mine"),
    ],
)
def test_each_role_lands_where_its_work_starts(client, make_person, csrf_token, roles, home):
    person = make_person(*roles)
    client.post("/auth/login", data={"username": person.username, "password": person.password, "csrf_token": csrf_token()})
    assert client.get("/").headers["Location"] == home


def test_one_top_bar_link_is_current_on_a_page(client, login):
    """Crowd and My tasks are both the crowd's pages: only the page's own link is current."""
    import re

    login("admin")
    page = client.get("/crowd/batches").get_data(as_text=True)
    current = re.findall(r'<a href="([^"]+)" aria-current="page">', page)
    assert current == ["/crowd/batches"]


def test_login_with_a_wrong_password_fails(client, make_person, csrf_token):
    person = make_person("admin")
    response = client.post(
        "/auth/login", data={"username": person.username, "password": "not the password", "csrf_token": csrf_token()}
    )
    assert response.status_code == 200
    assert "Wrong username or password." in response.get_data(as_text=True)
    assert logged_in_as(client) is None
    assert client.get("/cards").status_code == 302


def test_login_as_an_unknown_person_gives_the_same_message(client, csrf_token):
    response = client.post("/auth/login", data={"username": "nobody", "password": "whatever1", "csrf_token": csrf_token()})
    assert "Wrong username or password." in response.get_data(as_text=True)
    assert logged_in_as(client) is None


def test_a_disabled_person_cannot_log_in(client, make_person, csrf_token):
    person = make_person("curator", active=False)
    response = client.post(
        "/auth/login", data={"username": person.username, "password": person.password, "csrf_token": csrf_token()}
    )
    assert response.status_code == 403 and "disabled" in response.get_data(as_text=True)
    assert logged_in_as(client) is None


def test_passwords_are_stored_hashed(app, make_person):
    person = make_person("curator")
    with app.app_context():
        stored = db.session.get(Person, person.id).password_hash
    assert person.password not in stored and stored.startswith(("scrypt:", "pbkdf2:"))


# --------------------------------------------------------------------------- next


def test_login_follows_a_local_next(client, make_person, csrf_token):
    person = make_person("curator")
    response = client.post(
        "/auth/login",
        data={"username": person.username, "password": person.password, "next": "/cards?state=pass", "csrf_token": csrf_token()},
    )
    assert response.headers["Location"] == "/cards?state=pass"


@pytest.mark.parametrize(
    "target",
    [
        "https://evil.example/",
        "//evil.example/",
        "/\\evil.example",
        "\\\\evil.example",
        "http:evil.example",
        "javascript:alert(1)",
        "cards",
        "/\t/evil.example",
    ],
)
def test_login_refuses_to_redirect_off_site(client, make_person, csrf_token, target):
    person = make_person("curator")
    response = client.post(
        "/auth/login", data={"username": person.username, "password": person.password, "next": target, "csrf_token": csrf_token()}
    )
    assert response.status_code == 302
    assert response.headers["Location"] == "/"


def test_safe_next_keeps_paths_on_this_site():
    assert safe_next("/cards/3?x=1") == "/cards/3?x=1"
    assert safe_next("") is None and safe_next(None) is None


def test_anonymous_visit_goes_to_login_with_next_and_comes_back(client, make_person, csrf_token):
    response = client.get("/cards?state=review")
    assert response.status_code == 302
    assert response.headers["Location"].startswith("/auth/login?next=")
    page = client.get(response.headers["Location"]).get_data(as_text=True)
    assert 'value="/cards?state=review"' in page
    person = make_person("exporter")
    done = client.post(
        "/auth/login",
        data={
            "username": person.username,
            "password": person.password,
            "next": "/cards?state=review",
            "csrf_token": csrf_token(),
        },
    )
    assert done.headers["Location"] == "/cards?state=review"


def test_anonymous_json_request_gets_401(client):
    response = client.get("/cards", headers={"Accept": "application/json"})
    assert response.status_code == 401
    assert response.get_json()["error"]["code"] == 401


# --------------------------------------------------------------------------- logout


def test_logout_with_the_token_logs_out(client, login, csrf_token):
    login("curator")
    token = csrf_token("/cards")  # the logout form in the top bar
    response = client.post("/auth/logout", data={"csrf_token": token})
    assert response.status_code == 302 and response.headers["Location"] == "/auth/login"
    assert logged_in_as(client) is None
    assert client.get("/cards").status_code == 302


@pytest.mark.parametrize("role", ROLES)
def test_logout_works_for_every_role(client, as_role, csrf_token, role):
    as_role(role)
    response = client.post("/auth/logout", data={"csrf_token": csrf_token("/auth/login")})
    assert response.status_code == 302
    assert logged_in_as(client) is None


def test_logout_is_post_only(client, login):
    login("curator")
    response = client.get("/auth/logout")
    assert response.status_code == 405 and "POST" in response.headers["Allow"]
    assert logged_in_as(client) is not None


def test_logout_without_a_csrf_token_is_refused_and_changes_nothing(client, login):
    person = login("curator")
    response = client.post("/auth/logout")
    assert response.status_code == 400
    assert "CSRF" in response.get_data(as_text=True)
    assert logged_in_as(client) == str(person.id)


def test_login_without_a_csrf_token_is_refused(app, client, make_person):
    assert app.config.get("WTF_CSRF_ENABLED", True)
    person = make_person("admin")
    response = client.post("/auth/login", data={"username": person.username, "password": person.password})
    assert response.status_code == 400
    assert logged_in_as(client) is None


# --------------------------------------------------------------------------- people


@pytest.mark.parametrize("role, expected", [(None, 302), ("annotator", 403), ("curator", 403), ("exporter", 403), ("admin", 200)])
def test_people_page_is_for_admins(client, as_role, role, expected):
    as_role(role)
    response = client.get("/auth/people")
    assert response.status_code == expected
    if expected == 403:
        assert "admin" in response.get_data(as_text=True)


def test_people_page_lists_people_with_roles(client, login, make_person):
    login("admin", username="root")
    make_person("curator", "exporter", username="ada")
    html = client.get("/auth/people").get_data(as_text=True)
    assert "ada" in html and "root" in html
    assert 'role role-curator">curator' in html and 'role role-exporter">exporter' in html


@pytest.mark.both_databases
def test_admin_adds_a_person_who_can_then_log_in(app, client, login, csrf_token):
    login("admin")
    response = client.post(
        "/auth/people",
        data={
            "username": "grace",
            "display_name": "Grace H",
            "password": "longenough1",
            "roles": ["curator", "exporter"],
            "csrf_token": csrf_token("/auth/people"),
        },
    )
    assert response.status_code == 302
    assert "grace" in client.get("/auth/people").get_data(as_text=True)
    with app.app_context():
        grace = db.session.scalar(select(Person).where(Person.username == "grace"))
        assert grace.roles == {"curator", "exporter"} and grace.check_password("longenough1")
    client.post("/auth/logout", data={"csrf_token": csrf_token("/auth/people")})
    client.post("/auth/login", data={"username": "grace", "password": "longenough1", "csrf_token": csrf_token()})
    assert logged_in_as(client) == str(grace.id)


@pytest.mark.both_databases
def test_adding_a_duplicate_username_is_a_form_error_not_a_500(app, client, login, csrf_token, make_person):
    login("admin")
    make_person("annotator", username="dup")
    response = client.post(
        "/auth/people",
        data={
            "username": "dup",
            "password": "longenough1",
            "roles": ["curator"],
            "csrf_token": csrf_token("/auth/people"),
        },
    )
    assert response.status_code == 409
    assert "already exists" in response.get_data(as_text=True)
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Person).where(Person.username == "dup")) == 1


@pytest.mark.both_databases
@pytest.mark.parametrize("username", ["DUP", "Dup", "dUP"])
def test_usernames_are_unique_ignoring_case_on_the_people_page(app, client, login, csrf_token, make_person, username):
    # Issue 32: "ADMIN" and "Admin" could be added beside "admin".
    login("admin")
    make_person("annotator", username="dup")
    form = {"username": username, "password": "longenough1", "roles": ["curator"], "csrf_token": csrf_token("/auth/people")}
    response = client.post("/auth/people", data=form)
    assert response.status_code == 409
    text = response.get_data(as_text=True)
    assert "A person called &#39;dup&#39; already exists" in text and "whatever their case" in text
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Person).where(func.lower(Person.username) == "dup")) == 1


@pytest.mark.both_databases
def test_the_database_refuses_a_username_differing_only_in_case(app, make_person):
    from sqlalchemy.exc import IntegrityError

    make_person("annotator", username="admin")
    with app.app_context():
        db.session.add(Person(username="ADMIN", display_name="x"))
        with pytest.raises(IntegrityError):
            db.session.commit()
        db.session.rollback()


def test_create_person_refuses_case_variants_in_any_alphabet(app, make_person):
    from core.people import PeopleError, create_person

    make_person("annotator", username="Ädmin")
    with app.app_context():
        with pytest.raises(PeopleError, match="'Ädmin' already exists") as refused:
            create_person("äDMIN", "longenough1", ["curator"])
        assert refused.value.status == 409
        assert create_person("ädmin-2", "longenough1", ["curator"]).username == "ädmin-2"


@pytest.mark.both_databases
def test_log_in_finds_the_username_ignoring_case(app, client, make_person, csrf_token):
    grace = make_person("curator", username="Grace")
    response = client.post(
        "/auth/login", data={"username": "gRACE", "password": grace.password, "csrf_token": csrf_token("/auth/login")}
    )
    assert response.status_code == 302 and logged_in_as(client) == str(grace.id)


@pytest.mark.parametrize(
    "form, message",
    [
        ({"username": "x", "password": "short", "roles": ["curator"]}, "at least 8"),
        ({"username": "x", "password": "longenough1"}, "at least one role"),
        ({"username": "bad name", "password": "longenough1", "roles": ["curator"]}, "letters, digits"),
        ({"username": "x", "password": "longenough1", "roles": ["emperor"]}, "not a valid choice"),
    ],
)
def test_invalid_person_forms_say_why(app, client, login, csrf_token, form, message):
    login("admin")
    response = client.post("/auth/people", data={**form, "csrf_token": csrf_token("/auth/people")})
    assert response.status_code == 400
    assert message in response.get_data(as_text=True)
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Person)) == 1


def test_adding_a_person_without_a_csrf_token_changes_nothing(app, client, login):
    login("admin")
    response = client.post("/auth/people", data={"username": "mallory", "password": "longenough1", "roles": ["admin"]})
    assert response.status_code == 400
    with app.app_context():
        assert db.session.scalar(select(Person).where(Person.username == "mallory")) is None


def test_role_required_rejects_unknown_roles_when_decorating():
    with pytest.raises(ValueError, match="Expected roles"):
        role_required("emperor")
    with pytest.raises(ValueError):
        role_required()


def test_nav_bar_shows_who_is_logged_in_and_their_roles(client, login):
    person = login("curator", "exporter")
    html = client.get("/cards").get_data(as_text=True)
    assert person.username.title() in html
    assert 'role role-curator">curator' in html and 'role role-exporter">exporter' in html
    assert ">Cards<" in html and ">People<" not in html
