"""``keystone bench probe``: hostile requests, the role-by-route matrix, races and kills, against
the demo served the way ``keystone serve`` serves it by default (gunicorn, one process per core;
SQLite), then a look at what the database and the release folder hold afterwards.

It builds the demo in a temporary folder (:func:`app.demo.build_demo`, what ``keystone demo``
runs before serving), starts ``python -m app serve`` on a free port in a child process, logs in
as each demo role over real HTTP (the login form and its CSRF token, as a browser does) and
sends, family by family:

- **hostile**: for every route of the app's URL map and each method it takes, ids that are no
  database id (``0``, ``-1``, ``1_0``, ``５``, ``²``, 2**63, 5,000 digits), path traversal and
  NUL characters in its other parts, and for each form or JSON door: no or a forged CSRF token,
  malformed JSON, wrong types, huge and over-long bodies, hostile ids in id fields,
  spreadsheet formulas in free text, usernames differing from an existing one only in case;
- **role-by-route**: every route with every role (anonymous, annotator, curator, exporter,
  admin); a role the route is not for must get 401, 403 or a redirect to the login page, a
  role it is for must not;
- **concurrency**: two publishes of one previewed release at once (one release, one refusal
  with a sentence), four identical create-batch submits at once (one batch), a crowd answer
  submitted twice at once (stored once);
- **kills**: a publish killed after moving its folder into place (``KEYSTONE_TEST_PAUSE``) and
  one killed at a random moment, then ``verify`` and a publish that must go through; a
  ``keystone run`` killed mid-way, then rerun (no card computed twice, no claim left).

Afterwards, against the database and the release folder: no batch made from a hostile id, no
second user differing only in case, no spreadsheet formula left live in ``answers.csv`` or
``aggregates.csv`` (web and CLI exports), no release that was not previewed, no release folder
the catalogue does not know, every release verified. Each such finding counts as "wrongly
stored". The exit status is 1 when any request got a 5xx or anything was wrongly stored.
"""

from __future__ import annotations

import contextlib
import csv
import html
import http.client
import inspect
import io
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from html.parser import HTMLParser
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlencode

import click

REPO = Path(__file__).resolve().parents[1]

ROLES = ("anonymous", "annotator", "curator", "exporter", "admin")
# Ids no database row has, in every spelling Python's int() or str.isdigit() would take.
HOSTILE_IDS = ("0", "-1", "1_0", "\uff15", "\u00b2", "9223372036854775808", "9" * 5000)
QUICK_HOSTILE_IDS = ("1_0", "\uff15", "9223372036854775808")
# Other path parts: traversal (raw and encoded), a NUL, an over-long name.
HOSTILE_PARTS = ("../../keystone.sqlite3", "..%2F..%2Fkeystone.sqlite3", "a%00b", "x" * 300)
QUICK_HOSTILE_PARTS = ("../../keystone.sqlite3", "a%00b")
FORMULA = '=HYPERLINK("http://x")'
MISSING_ID = "2147483647"  # the largest id both databases hold: a well-formed id of no row
HUGE_TEXT = "x" * 200_000
OVER_LONG_BYTES = 2 * 1024 * 1024  # past the 1 MiB request limit
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
LOGIN_PATH = "/auth/login"

# What each form posts (the names its template uses): free text, ids, and the rest.
FORM_FIELDS: dict[str, dict[str, str]] = {
    "auth.login": {"username": "text", "password": "text", "next": "text"},
    "auth.people": {"username": "text", "password": "text", "display_name": "text", "roles": "choice"},
    "auth.person_password": {"password": "text"},
    "auth.person_roles": {"roles": "choice"},
    "auth.person_active": {"active": "choice"},
    "crowd.new_batch": {
        "kind": "choice",
        "cards": "ids",
        "answers_per_item": "id",
        "gold_rate": "number",
        "request_key": "text",
    },
    "crowd.new_invite": {"name": "text"},
    "crowd.check_submissions": {"participants": "text"},
    "crowd.flag_worker": {"flagged": "choice"},
    "exports.preview": {"min_grade": "choice", "formats": "choice", "notes": "text"},
    "exports.publish": {
        "min_grade": "choice",
        "formats": "choice",
        "notes": "text",
        "plan_digest": "text",
        "planned_version": "text",
        "planned_cards": "ids",
    },
    "review.bulk": {"item": "ids", "action": "choice", "grade": "choice", "note": "text"},
    "review.decide_card": {"choice": "choice", "version": "id", "note": "text"},
    "review.orientation_card": {"upside_down": "choice", "inverted": "choice", "swapped": "choice", "note": "text"},
    "review.undo": {"version": "id"},
    "review.dispute": {"left_x0": "number", "left_y0": "number", "right_x1": "number", "note": "text"},
}
# Crowd API bodies with the right shape and the wrong types.
WRONG_TYPES = (
    {"kind": 5},
    {"kind": ["judge"]},
    {"token": [], "answer": "yes", "key": {}},
    {"token": "x" * 5000, "answer": {"is_stereo": "yes"}, "key": 1},
    {"token": None, "answer": {"left": [1e308, "a", None, -1], "right": True}, "key": "k"},
)
MALFORMED_JSON = ('{"kind": "judge"', "[" * 5000, '{"kind": NaN}', "\ufeff{}", '"\\ud800"')


# ---------------------------------------------------------------------------------------------
# Tallies


@dataclass
class Family:
    """One family's counts; each finding is kept as a line saying what was sent and what came back."""

    name: str
    sent: int = 0
    server_errors: list[str] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    wrongly_stored: list[str] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        return {
            "requests": self.sent,
            "5xx": len(self.server_errors),
            "unexpected": len(self.unexpected),
            "wrongly_stored": len(self.wrongly_stored),
            "server_errors_seen": self.server_errors[:20],
            "unexpected_seen": self.unexpected[:20],
            "wrongly_stored_seen": self.wrongly_stored[:20],
        }


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    body: bytes

    @property
    def text(self) -> str:
        return self.body.decode("utf-8", "replace")

    @property
    def location(self) -> str:
        return self.headers.get("location", "")


def to_login(answer: Answer) -> bool:
    """A refusal to someone not logged in: 401, or a redirect to the login page."""
    return answer.status == 401 or (answer.status in (302, 303) and LOGIN_PATH in answer.location)


def refused_to_role(answer: Answer) -> bool:
    return answer.status == 403 or to_login(answer)


# ---------------------------------------------------------------------------------------------
# HTTP, as a browser or a script would speak it (http.client: no path normalisation)


class _Inputs(HTMLParser):
    """Every <input>'s name and value, grouped by the id of the <form> it is in ("" outside)."""

    def __init__(self) -> None:
        super().__init__()
        self.forms: dict[str, list[tuple[str, str]]] = {}
        self._form = ""

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = {k: v or "" for k, v in attrs}
        if tag == "form":
            self._form = values.get("id", "") or values.get("action", "")
        elif tag == "input" and values.get("name"):
            self.forms.setdefault(self._form, []).append((values["name"], values.get("value", "")))

    def handle_endtag(self, tag: str) -> None:
        if tag == "form":
            self._form = ""


def form_inputs(html: str, form: str) -> list[tuple[str, str]]:
    """The inputs of the form whose id (or action) is ``form`` on a page."""
    parser = _Inputs()
    parser.feed(html)
    return parser.forms.get(form, [])


FLASH = re.compile(r'class="flash flash-error"[^>]*>([^<]+)<')
CSRF_INPUT = re.compile(r'name="csrf_token"[^>]*value="([^"]+)"|value="([^"]+)"[^>]*name="csrf_token"')


class Browser:
    """One person's cookies and CSRF token against the served app."""

    def __init__(self, port: int, role: str) -> None:
        self.port, self.role = port, role
        self.cookies: dict[str, str] = {}
        self.csrf = ""

    def send(
        self,
        method: str,
        path: str,
        *,
        form: Iterable[tuple[str, str]] | dict[str, str] | None = None,
        json_body: Any = None,
        raw: bytes | None = None,
        content_type: str | None = None,
        headers: dict[str, str] | None = None,
        csrf: bool = True,
        timeout: float = 120,
    ) -> Answer:
        head = {"Accept": "text/html,*/*", **(headers or {})}
        body: bytes | None = raw
        if form is not None:
            pairs = list(form.items()) if isinstance(form, dict) else list(form)
            if csrf and self.csrf and not any(name == "csrf_token" for name, _ in pairs):
                pairs.append(("csrf_token", self.csrf))
            body = urlencode(pairs).encode()
            content_type = content_type or "application/x-www-form-urlencoded"
        elif json_body is not None:
            body = json.dumps(json_body, allow_nan=True).encode()
            content_type = content_type or "application/json"
        if content_type:
            head["Content-Type"] = content_type
        if csrf and self.csrf and method == "POST" and form is None:
            head.setdefault("X-CSRFToken", self.csrf)
        if self.cookies:
            head["Cookie"] = "; ".join(f"{k}={v}" for k, v in self.cookies.items())
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=timeout)
        try:
            connection.request(method, path, body=body, headers=head)
            response = connection.getresponse()
            data = response.read()
        except (ConnectionError, http.client.HTTPException) as exc:
            # The server closed the connection on a body it refused before reading it all.
            return Answer(0, {}, f"connection closed: {exc}".encode())  # status 0: no HTTP answer
        finally:
            connection.close()
        for name, value in response.getheaders():
            if name.lower() == "set-cookie":
                pair = value.split(";", 1)[0]
                key, _, cookie = pair.partition("=")
                if "max-age=0" in value.lower() or "expires=thu, 01 jan 1970" in value.lower():
                    self.cookies.pop(key.strip(), None)
                else:
                    self.cookies[key.strip()] = cookie
        return Answer(response.status, {k.lower(): v for k, v in response.getheaders()}, data)

    def take_csrf(self, answer: Answer) -> None:
        found = CSRF_INPUT.search(answer.text)
        if found:
            self.csrf = found.group(1) or found.group(2)

    def fetch_csrf(self, path: str) -> None:
        """The CSRF token of the page at ``path`` (redirects followed), bound to this session."""
        for _ in range(4):
            answer = self.send("GET", path)
            if answer.status not in (301, 302, 303) or not answer.location:
                break
            path = re.sub(r"^https?://[^/]+", "", answer.location)
        self.take_csrf(answer)
        if not self.csrf:
            raise click.ClickException(f"no CSRF token on {path} for {self.role}")

    def log_in(self, username: str, password: str) -> None:
        self.fetch_csrf(LOGIN_PATH)
        done = self.send("POST", LOGIN_PATH, form={"username": username, "password": password, "next": ""})
        if done.status not in (302, 303):
            raise click.ClickException(f"could not log in as {username}: {done.status} {done.text[:200]}")
        self.csrf = ""  # logging in starts a new session, with a new token
        self.fetch_csrf("/")


# ---------------------------------------------------------------------------------------------
# Routes


@dataclass(frozen=True)
class Route:
    rule: str
    endpoint: str
    methods: tuple[str, ...]
    arguments: tuple[tuple[str, str], ...]  # (name, converter)
    roles: tuple[str, ...] | None  # role_required's roles; None: no role check at the door


def required_roles(view: Callable[..., Any]) -> tuple[str, ...] | None:
    """The roles ``core.auth.role_required`` gave a view (read from its closure), or None."""
    seen: Callable[..., Any] | None = view
    while seen is not None:
        try:
            roles = inspect.getclosurevars(seen).nonlocals.get("roles")
        except (TypeError, ValueError):
            roles = None
        if isinstance(roles, tuple) and all(isinstance(role, str) for role in roles):
            return roles
        seen = getattr(seen, "__wrapped__", None)
    return None


ARGUMENT = re.compile(r"<(?:(\w+)(?:\([^)]*\))?:)?(\w+)>")


def app_routes(app: Any) -> list[Route]:
    """Every rule of the app's URL map with its methods (HEAD and OPTIONS aside) and its doors."""
    routes = []
    for rule in sorted(app.url_map.iter_rules(), key=lambda r: (r.rule, r.endpoint)):
        arguments = tuple((name, converter or "default") for converter, name in ARGUMENT.findall(rule.rule))
        methods = tuple(sorted(set(rule.methods or ()) - {"HEAD", "OPTIONS"}))
        routes.append(Route(rule.rule, rule.endpoint, methods, arguments, required_roles(app.view_functions[rule.endpoint])))
    return routes


def fill(rule: str, values: dict[str, str]) -> str:
    """``rule`` with each ``<converter:name>`` replaced by ``values[name]`` (percent-encoded
    unless it is already; ``/`` kept, so traversal reaches the server as written)."""

    def one(match: re.Match[str]) -> str:
        value = values[match.group(2)]
        return value if "%" in value else quote(value, safe="/")

    return ARGUMENT.sub(one, rule)


def role_may(route: Route, role: str) -> bool | None:
    """Whether ``role`` may use ``route`` (admins may do everything); None when the door does not say."""
    if route.roles is None:
        return None
    if role == "anonymous":
        return False
    return role == "admin" or role in route.roles


# ---------------------------------------------------------------------------------------------
# The demo instance and its server


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class Instance:
    folder: Path

    @property
    def database(self) -> Path:
        return self.folder / "keystone.sqlite3"

    @property
    def releases(self) -> Path:
        return self.folder / "releases"

    def config(self) -> dict[str, Any]:
        return {
            "SQLALCHEMY_DATABASE_URI": f"sqlite:///{self.database}",
            "KEYSTONE_DATA_DIR": str(self.folder / "data"),
            "KEYSTONE_RELEASES_DIR": str(self.releases),
        }

    def env(self, **extra: str) -> dict[str, str]:
        """The environment a ``python -m app ...`` child needs to use this instance, and only it."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("KEYSTONE_")}
        env.update(
            KEYSTONE_INSTANCE_PATH=str(self.folder),
            KEYSTONE_DATABASE_URL=f"sqlite:///{self.database}",
            KEYSTONE_DATA_DIR=str(self.folder / "data"),
            KEYSTONE_RELEASES_DIR=str(self.releases),
            PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH", "")])),
            **extra,
        )
        return env

    def keystone(self, *args: str, timeout: float = 300, **env: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "app", *args],
            cwd=REPO,
            env=self.env(**env),
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    def app(self) -> Any:
        from app import create_app

        return create_app(self.config(), instance_path=self.folder)


def build_instance(folder: Path, echo: Callable[[str], None]) -> tuple[Instance, dict[str, str]]:
    """The demo in ``folder`` (built by ``keystone demo``'s own builder) and its logins."""
    from app.demo import build_demo

    instance = Instance(folder)
    folder.mkdir(parents=True, exist_ok=True)
    app = instance.app()
    with app.app_context():
        summary = build_demo(folder, workers=2, echo=lambda _line: None)
    echo(f"demo built in {summary['seconds']:.1f} s in {folder}")
    return instance, dict(summary["logins"])


@contextlib.contextmanager
def served(instance: Instance, echo: Callable[[str], None]) -> Iterator[int]:
    """``python -m app serve`` with its defaults on a free port; yields the port once it answers."""
    port = free_port()
    log = (instance.folder / "server.log").open("w")
    server = subprocess.Popen(
        [sys.executable, "-m", "app", "serve", "--port", str(port)],
        cwd=REPO,
        env=instance.env(),
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            if server.poll() is not None:
                raise click.ClickException(f"the server stopped: {(instance.folder / 'server.log').read_text()[-2000:]}")
            with contextlib.suppress(OSError):
                if Browser(port, "anonymous").send("GET", LOGIN_PATH, timeout=5).status == 200:
                    break
            if time.monotonic() > deadline:
                raise click.ClickException("the server did not answer within 120 s")
            time.sleep(0.3)
        echo(f"serving on 127.0.0.1:{port} (python -m app serve, its defaults)")
        yield port
    finally:
        server.terminate()  # gunicorn's master stops its workers on SIGTERM
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait(10)
        log.close()


# ---------------------------------------------------------------------------------------------
# The probe


@dataclass
class Probe:
    instance: Instance
    port: int
    logins: dict[str, str]
    quick: bool
    echo: Callable[[str], None]
    families: dict[str, Family] = field(default_factory=dict)
    browsers: dict[str, Browser] = field(default_factory=dict)
    routes: list[Route] = field(default_factory=list)
    samples: dict[str, str] = field(default_factory=dict)
    notes: dict[str, Any] = field(default_factory=dict)

    def family(self, name: str) -> Family:
        return self.families.setdefault(name, Family(name))

    def check(
        self, family: str, what: str, answer: Answer, allowed: Callable[[Answer], bool] | Iterable[int] | None = None
    ) -> Answer:
        """Count ``answer``: a 5xx is always a finding; ``allowed`` (statuses or a test) says what else is."""
        tally = self.family(family)
        tally.sent += 1
        line = f"{what} -> {answer.status} {answer.text[:160]!r}"
        if answer.status >= 500:
            tally.server_errors.append(line)
        elif allowed is not None:
            ok = allowed(answer) if callable(allowed) else answer.status in set(allowed)
            if not ok:
                tally.unexpected.append(line)
        return answer

    def wrong(self, family: str, finding: str) -> None:
        self.family(family).wrongly_stored.append(finding)

    # -- set-up -----------------------------------------------------------------------------

    def log_in_everyone(self) -> None:
        self.browsers["anonymous"] = Browser(self.port, "anonymous")
        self.browsers["anonymous"].fetch_csrf(LOGIN_PATH)
        for role in ROLES[1:]:
            browser = Browser(self.port, role)
            browser.log_in(role, self.logins[role])
            self.browsers[role] = browser

    def load_samples(self) -> None:
        """Real ids and names for the routes' parts, so the role matrix reaches the views."""
        from sqlalchemy import select

        from annotation.models import Aggregate, Batch
        from core.db import db
        from core.models import Card, Person
        from exports.models import Release

        app = self.instance.app()
        self.routes = app_routes(app)
        with app.app_context():
            card = db.session.scalar(select(Card.id).order_by(Card.id))
            batch = db.session.scalar(select(Batch.id).order_by(Batch.id))
            aggregate = db.session.scalar(select(Aggregate.id).order_by(Aggregate.id))
            person = db.session.scalar(select(Person.id).order_by(Person.id))
            version = db.session.scalar(select(Release.version).order_by(Release.id))
        self.samples = {
            "card_id": str(card),
            "batch_id": str(batch),
            "aggregate_id": str(aggregate),
            "person_id": str(person),
            "worker_id": MISSING_ID,
            "version": version or "1.0.0",
            "stage": "rectify",
            "name": "README.md",
            "fmt": "mpo",
            "token": "no-such-token",
            "order": "lr",
            "filename": "style.css",
        }

    def url(self, route: Route, method: str, **override: str) -> str:
        """The route's path with sample parts; a POST gets ids of no row, so nothing real changes."""
        values = dict(self.samples)
        if method == "POST":
            values.update({name: MISSING_ID for name, converter in route.arguments if converter == "int"})
        values.update(override)
        return fill(route.rule, values)

    def browser_for(self, route: Route) -> Browser:
        """Who sends hostile requests to a route: someone it lets in (admins pass every role check)."""
        return self.browsers["admin" if route.roles is not None else "anonymous"]

    # -- role by route ----------------------------------------------------------------------

    def role_by_route(self) -> None:
        for route in self.routes:
            for method in route.methods:
                for role in ROLES:
                    if route.endpoint == "auth.logout":
                        continue  # the sessions are needed afterwards; logging out is checked last
                    path = self.url(route, method)
                    browser = self.browsers[role]
                    answer = browser.send(method, path, form={} if method == "POST" else None)
                    may = role_may(route, role)
                    what = f"{role} {method} {path}"
                    if may is None:
                        self.check("role-by-route", what, answer)
                    elif may:
                        self.check("role-by-route", what, answer, lambda a: not refused_to_role(a))
                    else:
                        self.check("role-by-route", what, answer, refused_to_role)

    # -- hostile ----------------------------------------------------------------------------

    def hostile(self) -> None:
        from sqlalchemy import func, select

        from annotation.models import Batch
        from core.db import db
        from exports.models import Release

        app = self.instance.app()
        with app.app_context():
            batches_before = db.session.scalar(select(func.count()).select_from(Batch))
            releases_before = db.session.scalar(select(func.count()).select_from(Release))

        ids = QUICK_HOSTILE_IDS if self.quick else HOSTILE_IDS
        parts = QUICK_HOSTILE_PARTS if self.quick else HOSTILE_PARTS
        for route in self.routes:
            browser = self.browser_for(route)
            for method in route.methods:
                for name, converter in route.arguments:
                    for value in ids if converter == "int" else parts:
                        path = self.url(route, method, **{name: value})
                        answer = browser.send(method, path, form={} if method == "POST" else None)
                        self.check("hostile", f"{browser.role} {method} {path[:120]}", answer, self._refused_part)
                if "POST" in route.methods and method == "POST":
                    self._hostile_bodies(route, browser)

        self._duplicate_case_usernames()

        with app.app_context():
            batches_after = db.session.scalar(select(func.count()).select_from(Batch))
            releases_after = db.session.scalar(select(func.count()).select_from(Release))
        if batches_after != batches_before:
            self.wrong("hostile", f"{batches_after - batches_before} batch(es) created by hostile create-batch forms")
        if releases_after != releases_before:
            self.wrong("hostile", f"{releases_after - releases_before} release(s) published by hostile publish forms")

    @staticmethod
    def _refused_part(answer: Answer) -> bool:
        # 404 (no such row or file), 400 (NUL, gunicorn's line limit), 405, 414; never the file.
        leaked = answer.body.startswith(b"SQLite format 3")
        return answer.status in (400, 404, 405, 414) and not leaked

    def _hostile_bodies(self, route: Route, browser: Browser) -> None:
        path = self.url(route, "POST")
        fields = FORM_FIELDS.get(route.endpoint, {})
        send = browser.send
        what = f"{browser.role} POST {path}"
        api = path.startswith("/crowd/api/")
        # CSRF: none, forged. The crowd API has no cookie session (its token is its credential).
        self.check("hostile", f"{what} without a CSRF token", send("POST", path, form={}, csrf=False), range(400, 500))
        forged = send("POST", path, form={"csrf_token": "forged." + "A" * 40})
        self.check("hostile", f"{what} with a forged CSRF token", forged, range(400, 500))
        # Malformed JSON and wrong types (the CSRF header is sent, so forms get past it).
        bodies = MALFORMED_JSON[:2] if self.quick else MALFORMED_JSON
        for text in bodies:
            answer = send("POST", path, raw=text.encode("utf-8", "surrogatepass"), content_type="application/json")
            self.check("hostile", f"{what} malformed JSON {text[:20]!r}", answer, range(300, 500))
        for document in WRONG_TYPES[:2] if self.quick else WRONG_TYPES:
            answer = send("POST", path, json_body=document)
            self.check("hostile", f"{what} JSON {json.dumps(document)[:40]}", answer, range(200, 500))
        # Over-long body: 413 before anything reads it.
        answer = send("POST", path, raw=b"a=" + b"x" * OVER_LONG_BYTES, content_type="application/x-www-form-urlencoded")
        # 413, or the connection closed before the server read it all (status 0): refused either way.
        self.check("hostile", f"{what} {OVER_LONG_BYTES:,} bytes", answer, (413, 0))
        if api:
            return
        # NUL characters, huge text, hostile ids and formulas in each field.
        answer = send("POST", path, form={name: "a\x00b" for name in fields} or {"x": "\x00"})
        self.check("hostile", f"{what} NUL in every field", answer, (400,))
        if not self.quick:
            answer = send("POST", path, form=dict.fromkeys(fields, HUGE_TEXT))
            self.check("hostile", f"{what} 200,000 characters in every field", answer, range(200, 500))
        for name, kind in fields.items():
            values = (
                (QUICK_HOSTILE_IDS if self.quick else HOSTILE_IDS)
                if kind in ("id", "ids")
                else (FORMULA,)
                if kind == "text"
                else ("\uff15", "nan", "1e999")
                if kind == "number"
                else ("not-a-choice",)
            )
            for value in values:
                form = dict(self._plausible_form(route.endpoint))
                form[name] = f"{self.samples['card_id']},{value}" if kind == "ids" else value
                answer = send("POST", path, form=form)
                self.check("hostile", f"{what} {name}={value[:30]!r}", answer, range(200, 500))

    def _plausible_form(self, endpoint: str) -> dict[str, str]:
        """A form that would pass but for the field under test (cards from the review queue, ...)."""
        return {
            "crowd.new_batch": {"kind": "judge", "cards": self.samples["card_id"], "answers_per_item": "3", "gold_rate": "0"},
            "exports.preview": {"min_grade": "some", "formats": "parquet", "notes": "probe"},
            "exports.publish": {
                "min_grade": "some",
                "formats": "parquet",
                "notes": "probe",
                "plan_digest": "0" * 64,
                "planned_version": "9.9.9",
                "planned_cards": self.samples["card_id"],
            },
            "auth.people": {"username": "probe-person", "password": "x", "display_name": "Probe", "roles": "curator"},
        }.get(endpoint, {})

    def _duplicate_case_usernames(self) -> None:
        admin = self.browsers["admin"]
        for username in ("ADMIN", "Curator", "eXporter", " admin", "ANNOTATOR"):
            form = {"username": username, "password": "probe-password-123", "display_name": "x", "roles": "curator"}
            answer = admin.send("POST", "/auth/people", form=form)
            self.check("hostile", f"admin POST /auth/people username={username!r}", answer, range(400, 500))

    def _crowd_doors(self) -> None:
        """Formulas where the crowd's own text enters: Prolific's SESSION_ID, an invitee's name."""
        anonymous = self.browsers["anonymous"]
        for pid, study, session in (
            (FORMULA, "probe-study", "probe-session-1"),
            ("probe-pid", "probe-study", FORMULA),
            ("@probe", "+study", "-session"),
        ):
            query = urlencode({"PROLIFIC_PID": pid, "STUDY_ID": study, "SESSION_ID": session})
            answer = anonymous.send("GET", f"/crowd/prolific?{query}")
            self.check("hostile", f"anonymous GET /crowd/prolific?{query[:80]}", answer, range(200, 500))
            self.notes.setdefault("prolific_entries", []).append(answer.status)
            token = re.search(r'data-worker-token="([^"]+)"', answer.text)
            if token:
                self._answer_one(token.group(1), "hostile", f"prolific {session!r}")

    def _answer_one(self, worker_token: str, family: str, who: str) -> None:
        anonymous = self.browsers["anonymous"]
        headers = {"X-Crowd-Token": worker_token}
        fetched = anonymous.send("POST", "/crowd/api/next", json_body={"kind": "judge"}, headers=headers, csrf=False)
        self.check(family, f"{who}: POST /crowd/api/next", fetched, (200,))
        tasks = (json.loads(fetched.body) if fetched.status == 200 else {}).get("tasks") or []
        if tasks:
            body = {"token": tasks[0]["token"], "answer": _judge_answer(tasks[0]), "key": str(uuid.uuid4())}
            answer = anonymous.send("POST", "/crowd/api/submit", json_body=body, headers=headers, csrf=False)
            self.check(family, f"{who}: POST /crowd/api/submit", answer, (200, 201))

    # -- the loop (issue 32's done-when) ----------------------------------------------------

    def loop(self) -> None:
        """A curator changes the eye order of an accepted card and of a graded card waiting for
        review, in the browser's own forms. At once both are stale, the waiting one cannot be
        accepted, and a dry-run preview leaves the accepted one out; then, with no terminal, the
        server's background worker recomputes both with the new eye order and they wait for the
        curator again. ``notes["loop"]`` has the seconds that took."""
        from sqlalchemy import select
        from sqlalchemy.orm import selectinload

        from core.db import db
        from core.models import Card
        from review.models import CardReview
        from runs.card_state import card_states

        app = self.instance.app()

        def states(ids: list[int]) -> dict[int, Any]:
            with app.app_context():
                cards = list(db.session.scalars(select(Card).where(Card.id.in_(ids)).options(selectinload(Card.stage_results))))
                found = card_states(cards)
                reviews = {
                    r.card_id: r.decision for r in db.session.scalars(select(CardReview).where(CardReview.card_id.in_(ids)))
                }
                db.session.remove()
            return {card: (found[card], reviews.get(card)) for card in ids}

        with app.app_context():
            decided = list(db.session.scalars(select(CardReview.card_id).where(CardReview.decision.in_(("accepted", "changed")))))
            pending = list(db.session.scalars(select(CardReview.card_id).where(CardReview.decision == "pending")))
            db.session.remove()
        now = states(decided + pending)
        accepted = next((card for card in decided if not now[card][0].stale), None)
        waiting = next((card for card in pending if not now[card][0].blockers), None)
        if accepted is None or waiting is None:
            self.family("loop").unexpected.append(f"the demo has no accepted card ({accepted}) or clear waiting card ({waiting})")
            return
        curator, exporter = self.browsers["curator"], self.browsers["exporter"]
        flipped = {}
        started = time.perf_counter()
        for card in (accepted, waiting):
            used = now[card][0].orientation
            flipped[card] = not used["swapped"]
            form = {flag: "yes" if used[flag] else "no" for flag in ("upside_down", "inverted")}
            form |= {"swapped": "yes" if flipped[card] else "no", "note": "probe: the eyes are exchanged"}
            self.check(
                "loop",
                f"curator POST /review/cards/{card}/orientation",
                curator.send("POST", f"/review/cards/{card}/orientation", form=form),
                (303,),
            )
        looked = time.perf_counter() - started
        after = states([accepted, waiting])
        stale_at_once = {card: "rectify" in (after[card][0].stale or {}) or bool(after[card][0].recomputing) for card in after}
        page = self.check("loop", f"curator GET /review/cards/{waiting}", curator.send("GET", f"/review/cards/{waiting}"), (200,))
        version = re.search(r'data-version="(\d+)"', page.text)
        shown = re.search(r'data-results="([^"]*)"', page.text)
        refused = curator.send(
            "POST",
            f"/review/cards/{waiting}/decide",
            json_body={
                "action": "accept",
                "version": int(version.group(1)) if version else 0,
                "results": shown.group(1) if shown else None,
            },
            headers={"Accept": "application/json"},
        )
        self.check("loop", f"curator POST /review/cards/{waiting}/decide (stale)", refused, (409,))
        preview = exporter.send(
            "POST", "/releases/preview", form={"min_grade": "some", "formats": "keystonedepth", "notes": "probe: loop"}
        )
        self.check("loop", "exporter POST /releases/preview (after the change)", preview, (200,))
        left_out = f"card {accepted}: its rectify result is out of date" in html.unescape(preview.text)
        deadline = time.monotonic() + 300
        back_after = None
        while time.monotonic() < deadline:
            now = states([accepted, waiting])
            if all(
                not now[card][0].stale
                and now[card][1] == "pending"
                and not now[card][0].recomputing
                and (now[card][0].statuses["rectify"]["metrics"].get("orientation_used") or {}).get("swapped") is flipped[card]
                for card in now
            ):
                back_after = time.perf_counter() - started
                break
            time.sleep(0.5)
        self.notes["loop"] = {
            "accepted_card": accepted,
            "waiting_card": waiting,
            "changed_in_s": round(looked, 2),
            "stale_at_once": stale_at_once,
            "accept_refused": refused.status,
            "accepted_left_out_of_preview": left_out,
            "recomputed_and_waiting_after_s": None if back_after is None else round(back_after, 1),
        }
        if not all(stale_at_once.values()) and looked < 1.0:
            self.wrong("loop", f"not stale right after the eye order changed: {stale_at_once}")
        if not left_out:
            self.wrong("loop", f"a dry-run preview did not leave out accepted card {accepted} whose eye order changed")
        if back_after is None:
            self.wrong("loop", "the two cards were not recomputed and back with the curator within 300 s (no terminal)")

    # -- concurrency ------------------------------------------------------------------------

    def concurrency(self) -> None:
        self._batch_race()
        self._publish_race()
        self._answer_race()
        self._crowd_doors()  # once the batch race has opened tasks, so these sessions answer some

    def _at_once(self, calls: list[Callable[[], Answer]]) -> list[Answer]:
        barrier = threading.Barrier(len(calls))
        answers: list[Answer | None] = [None] * len(calls)

        def run(index: int) -> None:
            barrier.wait(timeout=60)
            answers[index] = calls[index]()

        threads = [threading.Thread(target=run, args=(i,), daemon=True) for i in range(len(calls))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=300)
        return [a if a is not None else Answer(0, {}, b"no answer within 300 s") for a in answers]

    def _batch_race(self) -> None:
        from sqlalchemy import func, select

        from annotation.models import Batch
        from core.db import db
        from core.models import Card

        curator = self.browsers["curator"]
        page = curator.send("GET", "/crowd/batches")
        self.check("concurrency", "curator GET /crowd/batches", page, (200,))
        key = dict(form_inputs(page.text, "/crowd/batches/new") or _inputs_anywhere(page.text)).get("request_key", "")
        app = self.instance.app()
        with app.app_context():
            cards = list(db.session.scalars(select(Card.id).where(Card.state == "pass").order_by(Card.id).limit(3)))
            before = db.session.scalar(select(func.count()).select_from(Batch))
        form = {
            "kind": "judge",
            "cards": ",".join(map(str, cards)),
            "answers_per_item": "3",
            "gold_rate": "0",
            "request_key": key,
            "csrf_token": curator.csrf,
        }
        answers = self._at_once([lambda: curator.send("POST", "/crowd/batches/new", form=form)] * 4)
        for answer in answers:
            self.check("concurrency", "4 x curator POST /crowd/batches/new (one request_key)", answer, (303,))
        with app.app_context():
            made = db.session.scalar(select(func.count()).select_from(Batch)) - before
            batch = db.session.scalar(select(Batch.id).order_by(Batch.id.desc()))
        self.notes["batch_race"] = {"statuses": [a.status for a in answers], "batches_made": made, "request_key": bool(key)}
        if made != 1:
            self.wrong("concurrency", f"4 identical create-batch submits made {made} batches (expected 1)")
        self.samples["probe_batch"] = str(batch)

    def _publish_race(self) -> None:
        from sqlalchemy import func, select

        from core.db import db
        from exports.models import Release

        exporter = self.browsers["exporter"]
        form = {"min_grade": "some", "formats": "parquet", "notes": "probe: two publishes at once"}
        preview = self.check(
            "concurrency", "exporter POST /releases/preview", exporter.send("POST", "/releases/preview", form=form), (200,)
        )
        fields = form_inputs(preview.text, "publish-form")
        if not fields:
            self.family("concurrency").unexpected.append("the preview offered no publish form (nothing new to publish?)")
            return
        app = self.instance.app()
        with app.app_context():
            before = db.session.scalar(select(func.count()).select_from(Release))
        answers = self._at_once([lambda: exporter.send("POST", "/releases/publish", form=fields)] * 2)
        statuses = sorted(a.status for a in answers)
        for answer in answers:
            self.check("concurrency", "2 x exporter POST /releases/publish (one preview)", answer, (303, 409))
        refusal = next((a for a in answers if a.status == 409), None)
        sentence = FLASH.search(refusal.text) if refusal is not None else None
        self.notes["publish_race_refusal"] = sentence.group(1)[:200] if sentence else None
        if statuses != [303, 409] or sentence is None or "publish" not in sentence.group(1):
            self.family("concurrency").unexpected.append(
                f"two publishes of one preview: statuses {statuses}, expected [303, 409] with a sentence"
            )
        with app.app_context():
            made = db.session.scalar(select(func.count()).select_from(Release)) - before
        self.notes["publish_race"] = {"statuses": statuses, "releases_made": made}
        if made != 1:
            self.wrong("concurrency", f"two publishes of one preview made {made} releases (expected 1)")

    def _answer_race(self) -> None:
        from sqlalchemy import func, select

        from annotation.models import Answer as CrowdAnswer
        from core.db import db

        annotator = self.browsers["annotator"]
        mine = annotator.send("GET", "/crowd/mine")
        self.check("concurrency", "annotator GET /crowd/mine", mine, (303,))
        page = annotator.send("GET", mine.location.replace(f"http://127.0.0.1:{self.port}", ""))
        self.check("concurrency", "annotator GET their invite link", page, (200,))
        token = re.search(r'data-worker-token="([^"]+)"', page.text)
        if not token:
            self.family("concurrency").unexpected.append("the annotator's page carried no worker token")
            return
        headers = {"X-Crowd-Token": token.group(1)}
        fetched = annotator.send("POST", "/crowd/api/next", json_body={"kind": "judge"}, headers=headers, csrf=False)
        self.check("concurrency", "annotator POST /crowd/api/next", fetched, (200,))
        tasks = (json.loads(fetched.body) if fetched.status == 200 else {}).get("tasks") or []
        if not tasks:
            self.family("concurrency").unexpected.append("no judge task open for the annotator (the batch race made none?)")
            return
        body = {"token": tasks[0]["token"], "answer": _judge_answer(tasks[0]), "key": str(uuid.uuid4())}
        app = self.instance.app()
        with app.app_context():
            before = db.session.scalar(select(func.count()).select_from(CrowdAnswer))
        answers = self._at_once(
            [lambda: annotator.send("POST", "/crowd/api/submit", json_body=body, headers=headers, csrf=False)] * 2
        )
        for answer in answers:
            self.check("concurrency", "2 x annotator POST /crowd/api/submit (one answer)", answer, (200, 201, 409))
        with app.app_context():
            stored = db.session.scalar(select(func.count()).select_from(CrowdAnswer)) - before
        self.notes["answer_race"] = {"statuses": sorted(a.status for a in answers), "answers_stored": stored}
        if stored != 1:
            self.wrong("concurrency", f"one answer submitted twice at once was stored {stored} times (expected 1)")
        # The formula-named invitee answers too, so answers.csv carries its name.
        curator = self.browsers["curator"]
        name = f'=HYPERLINK("http://x/{uuid.uuid4().hex[:8]}")'
        invited = curator.send("POST", "/crowd/invites", form={"name": name})
        self.check("concurrency", "curator POST /crowd/invites name=formula", invited, (303,))
        flashed = curator.send("GET", "/crowd/batches")
        link = re.search(r"/crowd/invite/([A-Za-z0-9._~-]+)", flashed.text.split("Invite link for", 1)[-1])
        if link:
            page = self.browsers["anonymous"].send("GET", f"/crowd/invite/{link.group(1)}")
            worker = re.search(r'data-worker-token="([^"]+)"', page.text)
            if worker:
                self._answer_one(worker.group(1), "concurrency", "the formula-named invitee")

    # -- kills ------------------------------------------------------------------------------

    def kills(self) -> None:
        self._kill_publish_paused()
        if not self.quick:
            self._kill_publish_at_random()
        self._kill_run()

    def _export(self, formats: str, **env: str) -> subprocess.Popen[str]:
        return subprocess.Popen(
            [sys.executable, "-m", "app", "export", "--out", str(self.instance.releases), "--format", formats, "--json"],
            cwd=REPO,
            env=self.instance.env(**env),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )

    def _release_folders(self) -> set[str]:
        return {p.name for p in self.instance.releases.iterdir() if p.is_dir() and not p.name.startswith(".")}

    def _after_a_killed_publish(self, formats: str, label: str, before: set[str]) -> None:
        """``keystone verify`` the folder the kill left in place (if any), then the same publish
        again must go through (nothing the kill left may block it)."""
        family = self.family("kills")
        for name in sorted(self._release_folders() - before):
            folder = self.instance.releases / name
            checked = self.instance.keystone("verify", str(folder), "--no-mlcroissant", "--json")
            family.sent += 1
            if checked.returncode != 0:
                family.unexpected.append(f"{label}: verify {folder.name} exit {checked.returncode}: {checked.stdout[-300:]}")
        again = self.instance.keystone("export", "--out", str(self.instance.releases), "--format", formats, "--json")
        family.sent += 1
        if again.returncode != 0:
            family.unexpected.append(f"{label}: the next publish failed (exit {again.returncode}): {again.stderr[-300:]}")
        else:
            self.notes.setdefault("kills", []).append({label: json.loads(again.stdout).get("version")})

    def _kill_publish_paused(self) -> None:
        paused = self.instance.folder / "paused"
        before = self._release_folders()
        child = self._export("webdataset", KEYSTONE_TEST_PAUSE=f"after-move:{paused}")
        deadline = time.monotonic() + 180
        while not paused.exists() and child.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        reached = paused.exists()
        os.killpg(child.pid, signal.SIGKILL)
        child.wait(30)
        stderr = child.stderr.read() if child.stderr else ""
        if child.stderr:
            child.stderr.close()
        if not reached:
            self.family("kills").unexpected.append(f"the paused publish never reached its pause: {stderr[-300:]}")
        self._after_a_killed_publish("webdataset", "publish killed after moving its folder", before)

    def _kill_publish_at_random(self) -> None:
        """SIGKILL a publish at a random moment while it writes (once its partial folder is there)."""
        rng = random.Random(7)
        for formats in ("stereo", "views"):
            before = self._release_folders()
            hidden = {p.name for p in self.instance.releases.iterdir() if p.name.startswith(".")}
            child = self._export(formats)
            started = time.monotonic()
            while child.poll() is None and time.monotonic() - started < 120:
                if any(p.name.startswith(".") and p.name not in hidden for p in self.instance.releases.iterdir()):
                    break  # writing: its .<version>.partial-* folder (or marker) exists
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 0.5))
            killed = child.poll() is None
            if killed:
                os.killpg(child.pid, signal.SIGKILL)
            after_s = round(time.monotonic() - started, 2)
            self.notes.setdefault("random_kills", []).append(
                {"formats": formats, "after_s": after_s, "killed_while_writing": killed}
            )
            child.wait(30)
            if child.stderr:
                child.stderr.close()
            if not killed:
                self.family("kills").unexpected.append(f"the {formats} publish finished before it could be killed")
            self._after_a_killed_publish(formats, f"publish killed at a random moment ({formats})", before)

    def _kill_run(self) -> None:
        """Ingest more demo cards, kill ``keystone run`` once some results are written, rerun it."""
        from sqlalchemy import func, select

        from core.db import db
        from core.models import Card, StageResult
        from runs.claims import StageClaim
        from simulation.cards import make_demo_cards, write_demo_cards

        family = self.family("kills")
        scans = self.instance.folder / "scans-probe"
        write_demo_cards(make_demo_cards(seed=11), scans)
        ingested = self.instance.keystone(
            "ingest", str(scans), "--collection", "probe", "--metadata", str(scans / "metadata.csv"), "--json"
        )
        family.sent += 1
        if ingested.returncode != 0:
            family.unexpected.append(f"ingest for the run kill failed: {ingested.stderr[-300:]}")
            return
        app = self.instance.app()
        with app.app_context():
            done_before = db.session.scalar(select(func.count()).select_from(StageResult))
        stages = ["--stages", "filter,orientation"] if self.quick else []
        run_args = [sys.executable, "-m", "app", "run", *stages, "--claim-ttl-s", "3", "--json"]
        child = subprocess.Popen(
            run_args,
            cwd=REPO,
            env=self.instance.env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        deadline = time.monotonic() + 300
        written = 0
        while child.poll() is None and time.monotonic() < deadline:
            with app.app_context():
                written = db.session.scalar(select(func.count()).select_from(StageResult)) - done_before
            if written >= 3:
                break
            time.sleep(0.1)
        finished_early = child.poll() is not None
        with contextlib.suppress(ProcessLookupError):
            os.killpg(child.pid, signal.SIGKILL)
        child.wait(30)
        if finished_early:
            family.unexpected.append("the run finished before it could be killed mid-way")
        with app.app_context():
            snapshot = {
                (row.card_id, row.stage, row.param_hash): (row.id, row.started_at)
                for row in db.session.scalars(select(StageResult))
            }
            claims_after_kill = db.session.scalar(select(func.count()).select_from(StageClaim))
        rerun = subprocess.run(
            run_args, cwd=REPO, env=self.instance.env(), capture_output=True, text=True, timeout=600, check=False
        )
        family.sent += 2
        self.notes["run_kill"] = {"results_before_kill": written, "claims_left_by_the_kill": claims_after_kill}
        if rerun.returncode != 0:
            family.unexpected.append(f"the rerun after the kill exited {rerun.returncode}: {rerun.stderr[-300:]}")
        with app.app_context():
            after = {
                (row.card_id, row.stage, row.param_hash): (row.id, row.started_at)
                for row in db.session.scalars(select(StageResult))
            }
            claims = db.session.scalar(select(func.count()).select_from(StageClaim))
            unprocessed = db.session.scalar(
                select(func.count())
                .select_from(Card)
                .where(~select(StageResult.id).where(StageResult.card_id == Card.id, StageResult.stage == "filter").exists())
            )
        again = [key for key, value in snapshot.items() if after.get(key) != value]
        if again:
            self.wrong("kills", f"{len(again)} card-stage result(s) computed again by the rerun, e.g. {again[0]}")
        if claims:
            self.wrong("kills", f"{claims} stage claim(s) left after the rerun finished")
        if unprocessed:
            self.wrong("kills", f"{unprocessed} card(s) without a filter result after the rerun")
        self.notes["run_kill"].update(results_after_rerun=len(after) - done_before, recomputed=len(again))

    # -- what is stored ---------------------------------------------------------------------

    def stored(self) -> None:
        from sqlalchemy import func, select

        from annotation.models import Batch
        from core.db import db
        from core.models import Person
        from exports.models import Release

        family = "stored"
        self.family(family)
        app = self.instance.app()
        with app.app_context():
            twins = db.session.execute(
                select(func.lower(Person.username), func.count()).group_by(func.lower(Person.username)).having(func.count() > 1)
            ).all()
            batches = list(db.session.scalars(select(Batch.id).order_by(Batch.id)))
            usernames = list(db.session.scalars(select(Person.username)))
            releases = {(r.version, r.path) for r in db.session.scalars(select(Release))}
            web_releases = db.session.scalar(select(func.count()).select_from(Release).where(Release.notes.like("probe%")))
        for name, count in twins:
            self.wrong(family, f"{count} people named {name!r} ignoring case")
        for name in usernames:
            if any(ord(c) < 32 or c in "\u200b\ufeff" for c in name) or name != name.strip():
                self.wrong(family, f"a username with control or invisible characters or outer spaces: {name!r}")
        if web_releases > 1:  # the race's one; a hostile publish form (forged digest, ...) must publish nothing
            self.wrong(family, f"{web_releases} releases published from the probe's web forms (1 was previewed and published)")
        # Every folder in the releases folder is a recorded release; no partial folder or marker is left.
        recorded = {Path(path).resolve() for _version, path in releases}
        for entry in sorted(self.instance.releases.iterdir()):
            if entry.resolve() not in recorded:
                self.wrong(family, f"{entry.name} in the releases folder is no recorded release")
        from exports.verify import verify_release

        for version, path in sorted(releases):
            if not Path(path).is_dir():
                self.wrong(family, f"release {version} is recorded but its folder {path} is missing")
                continue
            verified = verify_release(Path(path))
            if not verified.ok:
                self.wrong(family, f"release {version} does not verify: {verified.problems[:3]}")
        # answers.csv from the web, answers.csv and aggregates.csv from the CLI: no live formula.
        curator = self.browsers["curator"]
        quoted = 0
        for batch in batches:
            answer = curator.send("GET", f"/crowd/batches/{batch}/answers.csv")
            self.check(family, f"curator GET /crowd/batches/{batch}/answers.csv", answer, (200,))
            quoted += sum(cell.startswith("'") for row in csv.reader(io.StringIO(answer.text)) for cell in row)
            for cell in live_formulas(answer.text):
                self.wrong(family, f"web answers.csv of batch {batch}: live formula {cell[:60]!r}")
        probe_batch = self.samples.get("probe_batch")
        for batch in [str(b) for b in batches] if not self.quick else [probe_batch] if probe_batch else []:
            out = self.instance.folder / f"crowd-export-{batch}"
            self.instance.keystone("crowd", "aggregate", batch)
            exported = self.instance.keystone("crowd", "export", batch, "--out", str(out), "--json")
            self.family(family).sent += 2
            if exported.returncode != 0:
                self.family(family).unexpected.append(
                    f"crowd export {batch} exit {exported.returncode}: {exported.stderr[-200:]}"
                )
                continue
            for name in ("answers.csv", "aggregates.csv"):
                for cell in live_formulas((out / name).read_text()):
                    self.wrong(family, f"CLI {name} of batch {batch}: live formula {cell[:60]!r}")
        self.notes["formula_cells_quoted_in_web_answers_csv"] = quoted

    def log_out_everyone(self) -> None:
        for role in ROLES:
            browser = self.browsers[role]
            if role == "anonymous":
                browser.fetch_csrf(LOGIN_PATH)  # the crowd pages it visited started new sessions
            answer = browser.send("POST", "/auth/logout", form={})
            self.check("role-by-route", f"{role} POST /auth/logout", answer, (302, 303))
            if role != "anonymous":
                after = browser.send("GET", "/review/")
                self.check("role-by-route", f"{role} GET /review/ after logging out", after, to_login)


def _inputs_anywhere(html: str) -> list[tuple[str, str]]:
    parser = _Inputs()
    parser.feed(html)
    return [pair for pairs in parser.forms.values() for pair in pairs]


def _judge_answer(task: dict[str, Any]) -> dict[str, Any]:
    questions = task.get("questions") or ["is_stereo", "upside_down", "inverted"]
    names = [q["key"] if isinstance(q, dict) and "key" in q else q for q in questions]
    return {name: name == "is_stereo" for name in names if isinstance(name, str)} or {
        "is_stereo": True,
        "upside_down": False,
        "inverted": False,
    }


def live_formulas(text: str) -> list[str]:
    """Cells of a CSV a spreadsheet would run as formulas: text (not a number) starting with
    ``= + - @``, a tab or a carriage return, leading spaces looked past."""
    found = []
    for row in csv.reader(io.StringIO(text)):
        for cell in row:
            if not cell.lstrip(" ").startswith(FORMULA_STARTS):
                continue
            try:
                float(cell)
            except ValueError:
                found.append(cell)
    return found


# ---------------------------------------------------------------------------------------------
# The command


FAMILIES = ("hostile", "role-by-route", "loop", "concurrency", "kills", "stored")


def run_probe(folder: Path, *, quick: bool, echo: Callable[[str], None]) -> dict[str, Any]:
    clock = time.perf_counter()
    instance, logins = build_instance(folder, echo)
    with served(instance, echo) as port:
        probe = Probe(instance, port, logins, quick, echo)
        probe.log_in_everyone()
        probe.load_samples()
        for family in FAMILIES:
            probe.family(family)
        steps = (
            ("role-by-route", probe.role_by_route),
            ("hostile", probe.hostile),
            ("loop", probe.loop),
            ("concurrency", probe.concurrency),
            ("kills", probe.kills),
            ("stored", probe.stored),
        )
        for name, step in steps:
            started = time.perf_counter()
            step()
            echo(f"{name}: {probe.family(name).sent} requests in {time.perf_counter() - started:.1f} s")
        probe.log_out_everyone()
    log = (instance.folder / "server.log").read_text(errors="replace")
    families = {name: probe.families[name].as_json() for name in FAMILIES}
    return {
        "quick": quick,
        "routes": len(probe.routes),
        "families": families,
        "total": {key: sum(f[key] for f in families.values()) for key in ("requests", "5xx", "unexpected", "wrongly_stored")},
        "server_tracebacks": log.count("Traceback (most recent call last)"),
        "notes": probe.notes,
        "seconds": round(time.perf_counter() - clock, 1),
    }


def render_table(report: dict[str, Any]) -> str:
    lines = [f"{'family':<15} {'requests':>9} {'5xx':>5} {'unexpected':>11} {'wrongly stored':>15}"]
    rows = [*report["families"].items(), ("total", report["total"])]
    for name, row in rows:
        lines.append(f"{name:<15} {row['requests']:>9} {row['5xx']:>5} {row['unexpected']:>11} {row['wrongly_stored']:>15}")
    for name, row in report["families"].items():
        for key in ("server_errors_seen", "unexpected_seen", "wrongly_stored_seen"):
            for line in row[key][:5]:
                lines.append(f"  {name} {key.replace('_seen', '').replace('_', ' ')}: {line}")
    lines.append(f"{report['routes']} routes; server tracebacks in its log: {report['server_tracebacks']}; {report['seconds']} s")
    for name, note in report["notes"].items():
        lines.append(f"  {name}: {json.dumps(note, default=str)[:300]}")
    return "\n".join(lines)


@click.command("probe")
@click.option("--quick", is_flag=True, help="A few dozen hostile requests and the short kills (for tests).")
@click.option(
    "--dir",
    "folder",
    type=click.Path(path_type=Path, file_okay=False),
    help="Build the demo here and keep it (default: a temporary folder, removed afterwards).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_probe_command(quick: bool, folder: Path | None, as_json: bool) -> None:
    """Probe the served demo: hostile requests, every role on every route, races, kills; then
    what was stored. Exit 1 on any 5xx or anything wrongly stored."""

    def echo(line: str) -> None:
        click.echo(line, err=as_json)

    kept = folder is not None
    with contextlib.ExitStack() as stack:
        if folder is None:
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="keystone-probe-"))) / "demo"
        elif folder.exists() and any(folder.iterdir()):
            raise click.UsageError(f"{folder} is not empty: the probe builds a fresh demo there")
        report = run_probe(folder.resolve(), quick=quick, echo=echo)
        if as_json:
            click.echo(json.dumps(report, indent=2, default=str))
        else:
            click.echo(render_table(report))
        if kept:
            echo(f"the probed instance (its server's log in server.log): {folder}")
    if report["total"]["5xx"] or report["total"]["wrongly_stored"]:
        raise SystemExit(1)
