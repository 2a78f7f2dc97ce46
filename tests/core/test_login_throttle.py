"""Accounts: login throttling, sessions that end on the server, session expiry, the expired-form message.

Time is the app's ``KEYSTONE_CLOCK`` (a settable clock) wherever the app decides by time, so
windows and session lifetimes are crossed without sleeping; one test lets a real cookie expire.
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import func, select, text
from werkzeug.security import generate_password_hash

from app import create_app
from app.schema import upgrade
from core.db import db
from core.login_throttle import ThrottlePolicy, lockout_of, normalise_address
from core.models import AuthEvent, AuthEventTamperError, LoginThrottle, Person

_CSRF_INPUT = re.compile(r'<input[^>]*name="csrf_token"[^>]*value="([^"]+)"')
WINDOW = timedelta(minutes=15)


@dataclass
class SettableClock:
    now: datetime

    def __call__(self) -> datetime:
        return self.now

    def advance(self, **delta: float) -> None:
        self.now += timedelta(**delta)


@pytest.fixture
def clock(app) -> SettableClock:  # type: ignore[no-untyped-def]
    clock = SettableClock(datetime.now(UTC))
    app.config["KEYSTONE_CLOCK"] = clock
    return clock


def logged_in_as(client) -> str | None:  # type: ignore[no-untyped-def]
    with client.session_transaction() as session:
        return session.get("_user_id")


def token_of(client, url: str = "/auth/login") -> str:  # type: ignore[no-untyped-def]
    match = _CSRF_INPUT.search(client.get(url, follow_redirects=True).get_data(as_text=True))
    assert match, f"no csrf_token on {url}"
    return match.group(1)


def attempt(client, username: str, password: str, **kwargs):  # type: ignore[no-untyped-def]
    return client.post("/auth/login", data={"username": username, "password": password, "csrf_token": token_of(client)}, **kwargs)


def events(app, action: str | None = None) -> list[AuthEvent]:  # type: ignore[no-untyped-def]
    with app.app_context():
        query = select(AuthEvent).order_by(AuthEvent.id)
        if action:
            query = query.where(AuthEvent.action == action)
        rows = list(db.session.scalars(query))
        db.session.expunge_all()
        return rows


# --------------------------------------------------------------------------- throttling


@pytest.mark.both_databases
def test_the_sixth_wrong_password_is_refused_with_429_and_retry_after(app, client, make_person, clock):
    person = make_person("curator")
    for _ in range(5):
        response = attempt(client, person.username, "not the password")
        assert response.status_code == 200 and "Wrong username or password." in response.get_data(as_text=True)
    clock.advance(seconds=30)
    refused = attempt(client, person.username, "still not it")
    assert refused.status_code == 429
    assert refused.headers["Retry-After"] == str(15 * 60 - 30)
    html = refused.get_data(as_text=True)
    assert "Too many wrong passwords for this account" in html and "Try again in 15 minutes." in html
    assert 'name="csrf_token"' in html  # the login form is still there for later

    failed = events(app, "login_failed")
    assert [(e.username, e.person_id, e.reason, e.address) for e in failed] == [
        (person.username, person.id, "wrong password", "127.0.0.1")
    ] * 5
    [throttled] = events(app, "login_throttled")
    assert throttled.username == person.username and throttled.address == "127.0.0.1"
    assert throttled.reason == "account: 5 wrong passwords in the window; retry after 870 s"


@pytest.mark.both_databases
def test_the_right_password_during_a_lockout_is_refused_too(app, client, make_person, clock):
    person = make_person("admin")
    for _ in range(5):
        attempt(client, person.username, "guess")
    response = attempt(client, person.username, person.password)
    assert response.status_code == 429 and "Retry-After" in response.headers
    assert logged_in_as(client) is None
    assert events(app, "login") == []


@pytest.mark.both_databases
def test_the_lockout_ends_with_the_window_and_refused_attempts_do_not_extend_it(app, client, make_person, clock):
    person = make_person("curator")
    for _ in range(5):
        attempt(client, person.username, "guess")
    clock.advance(minutes=10)
    for _ in range(3):  # hammering during the lockout costs nothing and extends nothing
        response = attempt(client, person.username, "guess")
        assert response.status_code == 429 and response.headers["Retry-After"] == str(5 * 60)
    clock.advance(minutes=5, seconds=-1)
    assert attempt(client, person.username, person.password).headers["Retry-After"] == "1"
    clock.advance(seconds=1)
    response = attempt(client, person.username, person.password)
    assert response.status_code == 302 and logged_in_as(client) == str(person.id)
    assert len(events(app, "login_throttled")) == 4 and len(events(app, "login")) == 1


@pytest.mark.both_databases
def test_a_right_password_resets_the_account_count(app, client, make_person, clock):
    person = make_person("curator")
    for _ in range(4):
        attempt(client, person.username, "typo")
    assert attempt(client, person.username, person.password).status_code == 302
    client.post("/auth/logout", data={"csrf_token": token_of(client, "/cards")})
    for _ in range(4):
        assert attempt(client, person.username, "typo").status_code == 200
    assert attempt(client, person.username, person.password).status_code == 302


@pytest.mark.both_databases
def test_unknown_usernames_are_throttled_like_real_ones(app, client, clock):
    for _ in range(5):
        assert attempt(client, "nobody", "whatever1").status_code == 200
    response = attempt(client, "nobody", "whatever1")
    assert response.status_code == 429
    assert [e.reason for e in events(app, "login_failed")] == ["unknown username"] * 5


@pytest.mark.both_databases
def test_an_address_that_guesses_across_accounts_is_throttled(app, client, make_person, clock):
    app.config["KEYSTONE_LOGIN_FAILURES_PER_ADDRESS"] = 8
    people = [make_person("annotator") for _ in range(3)]
    answers = [attempt(client, people[i % 3].username, "spray-1234").status_code for i in range(9)]
    assert answers == [200] * 8 + [429]  # no account reached 5, the address reached 8
    response = attempt(client, people[0].username, people[0].password)
    assert response.status_code == 429 and "your network address" in response.get_data(as_text=True)
    # Another client address still may log in to the same account.
    other = app.test_client()
    elsewhere = {"REMOTE_ADDR": "192.0.2.7"}
    token = token_of(other)
    response = other.post(
        "/auth/login",
        data={"username": people[0].username, "password": people[0].password, "csrf_token": token},
        environ_base=elsewhere,
    )
    assert response.status_code == 302
    assert events(app, "login")[-1].address == "192.0.2.7"


@pytest.mark.both_databases
def test_successful_logins_do_not_use_up_an_address(app, client, make_person, clock):
    app.config["KEYSTONE_LOGIN_FAILURES_PER_ADDRESS"] = 3
    for _ in range(6):  # a shared office address: many people log in
        person = make_person("annotator")
        assert attempt(client, person.username, person.password).status_code == 302
        client.post("/auth/logout", data={"csrf_token": token_of(client, "/")})


@pytest.mark.both_databases
def test_every_server_process_counts_against_one_budget(app, client, database, tmp_path, make_person, clock):
    """A second app on the same database stands for another server process: it sees the lockout."""
    person = make_person("curator")
    for _ in range(5):
        attempt(client, person.username, "guess")
    other_process = create_app(
        {
            "TESTING": True,
            "SQLALCHEMY_DATABASE_URI": database,
            "SECRET_KEY": "test-secret",
            "KEYSTONE_DATA_DIR": str(tmp_path / "data"),
            "KEYSTONE_CLOCK": clock,
        }
    )
    try:
        response = attempt(other_process.test_client(), person.username, person.password)
        assert response.status_code == 429
    finally:
        with other_process.app_context():
            db.engine.dispose()


@pytest.mark.both_databases
def test_concurrent_guesses_cannot_outrun_the_count(app, make_person, clock):
    """Twelve guesses at once: each is counted before its password is checked, so exactly five
    are checked and seven refused, even though all twelve arrive before any check ends."""
    person = make_person("admin")
    clients = [app.test_client() for _ in range(12)]
    tokens = [token_of(c) for c in clients]
    start = threading.Barrier(len(clients))
    codes: list[int] = []

    def guess(index: int) -> None:
        start.wait()
        response = clients[index].post(
            "/auth/login", data={"username": person.username, "password": f"guess-{index}", "csrf_token": tokens[index]}
        )
        codes.append(response.status_code)

    threads = [threading.Thread(target=guess, args=(i,)) for i in range(len(clients))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert sorted(codes) == [200] * 5 + [429] * 7
    assert len(events(app, "login_failed")) == 5 and len(events(app, "login_throttled")) == 7


def test_throttle_rows_whose_window_ended_are_dropped_at_the_next_login(app, client, make_person, clock):
    person = make_person("curator")
    attempt(client, "someone-else", "guess")
    clock.advance(minutes=16)
    attempt(client, person.username, person.password)
    with app.app_context():
        subjects = set(db.session.scalars(select(LoginThrottle.subject)))
    assert "someone-else" not in subjects and person.username in subjects


def test_lockout_of_counts_only_inside_the_window():
    policy = ThrottlePolicy(window=WINDOW, per_account=5, per_address=30)
    started = datetime(2026, 11, 24, 12, 0, tzinfo=UTC)
    assert lockout_of("account", 4, started, started + timedelta(minutes=1), policy) is None
    locked = lockout_of("account", 5, started, started + timedelta(minutes=1), policy)
    assert locked is not None and locked.retry_after_s == 14 * 60 and locked.minutes == 14
    assert lockout_of("account", 5, started, started + WINDOW, policy) is None
    assert lockout_of("address", 29, started, started, policy) is None
    naive = started.replace(tzinfo=None)  # as SQLite returns it
    assert lockout_of("address", 30, naive, started + timedelta(seconds=899.2), policy).retry_after_s == 1
    with pytest.raises(ValueError, match="Expected a scope"):
        policy.budget("planet")


@pytest.mark.parametrize(
    "raw, key",
    [
        ("203.0.113.9", "203.0.113.9"),
        ("2001:db8:1:2:3:4:5:6", "2001:db8:1:2::/64"),
        ("2001:db8:1:2:ffff::1", "2001:db8:1:2::/64"),  # the same /64: one budget
        ("::ffff:198.51.100.4", "198.51.100.4"),
        ("fe80::1%eth0", "fe80::/64"),
        (None, "unknown"),
        ("not-an-address", "not-an-address"),
    ],
)
def test_addresses_are_throttled_by_host_or_ipv6_network(raw, key):
    assert normalise_address(raw) == key


def test_forwarded_for_is_ignored_unless_proxies_are_configured(app, client, make_person, clock, tmp_path, database):
    app.config["KEYSTONE_LOGIN_FAILURES_PER_ADDRESS"] = 2
    spoofed = {"X-Forwarded-For": "198.51.100.1"}
    attempt(client, "a", "guess", headers=spoofed)
    attempt(client, "b", "guess", headers={"X-Forwarded-For": "198.51.100.2"})
    assert attempt(client, "c", "guess", headers={"X-Forwarded-For": "198.51.100.3"}).status_code == 429

    behind_proxy = create_app(
        {
            "TESTING": True,
            "SQLALCHEMY_DATABASE_URI": database,
            "SECRET_KEY": "test-secret",
            "KEYSTONE_DATA_DIR": str(tmp_path / "data"),
            "KEYSTONE_CLOCK": clock,
            "KEYSTONE_TRUSTED_PROXIES": 1,
            "KEYSTONE_LOGIN_FAILURES_PER_ADDRESS": 2,
        }
    )
    try:
        proxied = behind_proxy.test_client()
        # The proxy appends the real client; whatever the client itself put first is not trusted.
        response = attempt(proxied, "d", "guess", headers={"X-Forwarded-For": "10.0.0.1, 203.0.113.50"})
        assert response.status_code == 200
        assert events(app, "login_failed")[-1].address == "203.0.113.50"
    finally:
        with behind_proxy.app_context():
            db.engine.dispose()


# --------------------------------------------------------------------------- sessions end on the server


def session_cookie(client) -> str:  # type: ignore[no-untyped-def]
    cookie = client.get_cookie("session")
    assert cookie is not None
    return cookie.value


@pytest.mark.both_databases
def test_a_copied_cookie_is_refused_after_logout(app, client, login, clock):
    person = login("curator")
    copied = app.test_client()
    copied.set_cookie("session", session_cookie(client))
    assert copied.get("/cards").status_code == 200  # the copy works while the session lasts

    client.post("/auth/logout", data={"csrf_token": token_of(client, "/cards")})
    response = copied.get("/cards", headers={"Accept": "text/html"})  # a browser's page load
    assert response.status_code == 302 and response.headers["Location"].startswith("/auth/login?next=")
    page = copied.get(response.headers["Location"]).get_data(as_text=True)
    assert "Your session has ended" in page
    assert copied.get("/cards").status_code == 302  # and stays refused

    [logout] = events(app, "logout")
    assert logout.person_id == person.id
    refused = events(app, "session_refused")
    assert refused and refused[0].person_id == person.id and refused[0].reason == "session ended"


@pytest.mark.both_databases
@pytest.mark.parametrize("change", ["password", "deactivate"])
def test_a_new_password_or_deactivation_ends_existing_sessions(app, client, login, change):
    person = login("curator")
    assert client.get("/cards").status_code == 200
    with app.app_context():
        stored = db.session.get(Person, person.id)
        before = stored.session_version
        if change == "password":
            stored.set_password("a brand new password")
        else:
            stored.active = False
        db.session.commit()
        assert db.session.get(Person, person.id).session_version == before + 1
    assert client.get("/cards").status_code == 302
    assert logged_in_as(client) is None


def test_a_new_person_starts_at_session_version_one(app, make_person):
    person = make_person("curator")
    with app.app_context():
        assert db.session.get(Person, person.id).session_version == 1


def test_logout_ends_the_persons_other_sessions_too(app, make_person):
    person = make_person("curator")
    laptop, phone = app.test_client(), app.test_client()
    for device in (laptop, phone):
        assert attempt(device, person.username, person.password).status_code == 302
    laptop.post("/auth/logout", data={"csrf_token": token_of(laptop, "/cards")})
    assert phone.get("/cards").status_code == 302


def test_a_session_from_before_session_versions_is_refused(app, client, login):
    login("curator")
    with client.session_transaction() as session:
        del session["_keystone_session_version"]
    assert client.get("/cards").status_code == 302


# --------------------------------------------------------------------------- expiry and cookies


@pytest.mark.both_databases
def test_a_session_expires_a_working_day_after_login(app, client, login, clock):
    assert app.permanent_session_lifetime == timedelta(hours=8)
    login("curator")
    clock.advance(hours=7, minutes=59)
    assert client.get("/cards").status_code == 200
    clock.advance(minutes=1, seconds=1)
    response = client.get("/cards?state=pass", headers={"Accept": "text/html"})
    assert response.status_code == 302 and response.headers["Location"] == "/auth/login?next=/cards?state%3Dpass"
    assert "Your session expired: log in again." in client.get(response.headers["Location"]).get_data(as_text=True)
    assert [e.reason for e in events(app, "session_refused")] == ["session expired"]


def test_the_session_cookie_is_httponly_lax_and_expires(app, client, make_person):
    person = make_person("curator")
    response = attempt(client, person.username, person.password)
    header = next(h for h in response.headers.getlist("Set-Cookie") if h.startswith("session="))
    assert "HttpOnly" in header and "SameSite=Lax" in header and "Secure" not in header
    expires = datetime.strptime(re.search(r"Expires=([^;]+)", header).group(1), "%a, %d %b %Y %H:%M:%S GMT")
    hours = (expires.replace(tzinfo=UTC) - datetime.now(UTC)).total_seconds() / 3600
    assert 7.9 < hours <= 8.0


def test_session_length_and_secure_cookies_come_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("KEYSTONE_SESSION_HOURS", "1.5")
    monkeypatch.setenv("KEYSTONE_SECURE_COOKIES", "1")
    application = create_app({"SQLALCHEMY_DATABASE_URI": f"sqlite:///{tmp_path / 'k.sqlite3'}"}, tmp_path / "instance")
    assert application.permanent_session_lifetime == timedelta(minutes=90)
    assert application.config["SESSION_COOKIE_SECURE"] is True
    assert application.config["SESSION_COOKIE_HTTPONLY"] is True
    assert application.config["SESSION_COOKIE_SAMESITE"] == "Lax"


@pytest.mark.parametrize(
    "name, value",
    [
        ("KEYSTONE_SESSION_HOURS", "a day"),
        ("KEYSTONE_SESSION_HOURS", "0"),
        ("KEYSTONE_LOGIN_FAILURES_PER_ACCOUNT", "0"),
        ("KEYSTONE_LOGIN_WINDOW_MINUTES", "-5"),
        ("KEYSTONE_TRUSTED_PROXIES", "one"),
    ],
)
def test_bad_account_settings_say_which_and_why(tmp_path, monkeypatch, name, value):
    monkeypatch.setenv(name, value)
    with pytest.raises(ValueError, match=f"Expected {name} to be a .*, got '{value}'"):
        create_app({}, tmp_path / "instance")


# --------------------------------------------------------------------------- an expired session on a form


@pytest.mark.both_databases
def test_a_form_posted_after_the_session_expired_says_so_and_links_to_login(app, client, login):
    login("admin")
    token = token_of(client, "/auth/people")
    client.delete_cookie("session")  # what the browser does when the cookie expires
    response = client.post(
        "/auth/people",
        data={"username": "grace", "password": "longenough1", "roles": ["curator"], "csrf_token": token},
        headers={"Referer": "http://localhost/auth/people"},
    )
    assert response.status_code == 400
    html = response.get_data(as_text=True)
    assert "Your session expired: log in again." in html and "CSRF" not in html
    assert '<a class="button" href="/auth/login?next=/auth/people">Log in again</a>' in html
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Person).where(Person.username == "grace")) == 0


def test_a_really_expired_cookie_gives_the_same_message(app, client, login):
    """The cookie itself, not only the login, is refused past the lifetime (Flask checks its signed age)."""
    login("admin")
    token = token_of(client, "/auth/people")
    app.permanent_session_lifetime = timedelta(seconds=1)
    time.sleep(2.1)
    response = client.post(
        "/auth/people", data={"username": "x", "csrf_token": token}, headers={"Referer": "http://localhost/auth/people?tab=add"}
    )
    assert response.status_code == 400
    html = response.get_data(as_text=True)
    assert "Your session expired: log in again." in html and "/auth/login?next=/auth/people?tab%3Dadd" in html


def test_the_expired_message_as_json(client, login):
    login("admin")
    token = token_of(client, "/auth/people")
    client.delete_cookie("session")
    response = client.post("/auth/logout", data={"csrf_token": token}, headers={"Accept": "application/json"})
    assert response.status_code == 400
    error = response.get_json()["error"]
    assert error["message"] == "Your session expired: log in again." and error["login_url"] == "/auth/login"


def test_the_login_form_itself_after_expiry_links_to_a_fresh_login_form(client):
    token = token_of(client, "/auth/login?next=/cards")
    client.delete_cookie("session")
    response = client.post(
        "/auth/login",
        data={"username": "a", "password": "b", "csrf_token": token},
        headers={"Referer": "http://localhost/auth/login?next=/cards"},
    )
    assert response.status_code == 400
    assert 'href="/auth/login?next=/cards"' in response.get_data(as_text=True)


def test_an_off_site_referer_is_not_offered_as_next(client, login):
    login("admin")
    token = token_of(client, "/auth/people")
    client.delete_cookie("session")
    response = client.post("/auth/people", data={"csrf_token": token}, headers={"Referer": "https://evil.example/x"})
    assert response.status_code == 400 and 'href="/auth/login"' in response.get_data(as_text=True)


def test_a_form_opened_before_logging_in_says_so(client, make_person):
    person = make_person("curator")
    token = token_of(client, "/auth/login")  # a second tab, still on the login page
    attempt(client, person.username, person.password)
    response = client.post(
        "/auth/login",
        data={"username": "x", "password": "y", "csrf_token": token},
        headers={"Referer": "http://localhost/auth/login"},
    )
    assert response.status_code == 400
    html = response.get_data(as_text=True)
    assert "This form was opened before you logged in. (Reload /auth/login and submit it again.)" in html
    assert "session expired" not in html.lower() and logged_in_as(client) == str(person.id)


def test_other_csrf_failures_keep_their_own_message(client, login):
    login("curator")
    token_of(client, "/cards")  # the session holds a token, the form sends another
    response = client.post("/auth/logout", data={"csrf_token": "forged"})
    assert response.status_code == 400
    html = response.get_data(as_text=True)
    assert "CSRF" in html and "session expired" not in html.lower()
    assert logged_in_as(client) is not None


# --------------------------------------------------------------------------- the trail


@pytest.mark.both_databases
def test_sign_in_events_are_append_only(app, client, make_person):
    person = make_person("curator")
    attempt(client, person.username, "guess")
    with app.app_context():
        row = db.session.scalars(select(AuthEvent)).one()
        row.reason = "nothing happened"
        with pytest.raises(AuthEventTamperError):
            db.session.flush()
        db.session.rollback()
        for statement in ("UPDATE auth_events SET reason = 'edited'", "DELETE FROM auth_events"):
            with pytest.raises(Exception, match="append-only"):
                with db.engine.begin() as connection:
                    connection.execute(text(statement))
        assert db.session.scalars(select(AuthEvent.reason)).all() == ["wrong password"]


@pytest.mark.both_databases
def test_people_from_before_the_migration_get_version_one_and_can_log_in(app, client):
    from alembic import command

    from app.schema import alembic_config

    with app.app_context():
        config = alembic_config(db.engine)
        with db.engine.begin() as connection:
            config.attributes["connection"] = connection
            command.downgrade(config, "0004")
        with db.engine.begin() as connection:
            connection.execute(
                text(
                    "INSERT INTO people (username, display_name, password_hash, active, created_at) "
                    "VALUES ('ada', 'Ada', :hash, :yes, CURRENT_TIMESTAMP)"
                ),
                {"hash": generate_password_hash("longenough1"), "yes": True},
            )
        upgrade(db.engine)
        assert db.session.scalar(select(Person.session_version).where(Person.username == "ada")) == 1
        db.session.remove()
    assert attempt(client, "ada", "longenough1").status_code == 302
    assert logged_in_as(client) is not None
    assert "Ada" in client.get("/").get_data(as_text=True)  # the loader accepts the session


def test_case_variants_of_a_username_share_one_budget():
    # Log-in finds usernames ignoring case, so "ADMIN" must not be a fresh budget of guesses at admin.
    from core.login_throttle import _keys

    assert _keys("ADMIN", "203.0.113.9") == _keys("admin", "203.0.113.9") == [("account", "admin"), ("address", "203.0.113.9")]
