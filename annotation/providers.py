"""Where workers come from: one :class:`CrowdProvider` seam behind invite links, Prolific and MTurk.

A provider turns the entry URL's parameters into a worker and says what happens when the
worker is done. The page then carries the worker's identity and session as a *signed token*
(never a session cookie): crowd pages live in third-party iframes (MTurk) where browsers drop
cookies. The session (:mod:`annotation.sessions`), not the participant id, bounds what the token
may touch, and the token ends with it: once the session is finished (``/crowd/finish``) or the
token is older than ``KEYSTONE_CROWD_TOKEN_HOURS`` (:func:`annotation.crowd_settings.token_lifetime_s`),
every API call with it is refused (410 finished, 401 expired). Opening the worker's link again
signs a fresh token: an invite link then starts a new session, a Prolific or MTurk link of a
finished session says it is finished (their session is one submission).
"""

from __future__ import annotations

import secrets
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol
from urllib.parse import urlencode, urlsplit

from flask import current_app
from itsdangerous import BadSignature, URLSafeSerializer
from sqlalchemy import bindparam, func, select

from core.db import db

from .crowd_settings import token_lifetime_s
from .labels import invite_statuses
from .models import Answer, CrowdSession, Worker
from .sessions import invite_session, open_session
from .task_errors import TaskError
from .workers import get_or_create_worker

TOKEN_SALT = "keystone-crowd-worker"
PROLIFIC_COMPLETION_URL = "https://app.prolific.com/submissions/complete"
MTURK_PREVIEW_ASSIGNMENT = "ASSIGNMENT_ID_NOT_AVAILABLE"
# Where MTurk may ask us to post the finished assignment (production and sandbox).
MTURK_SUBMIT_ORIGINS: tuple[str, ...] = ("https://www.mturk.com", "https://workersandbox.mturk.com")


@dataclass(frozen=True)
class Entry:
    """A worker's way in: who they are and in which session (None in MTurk preview), and the provider's context."""

    provider: str
    worker: Worker | None
    context: dict[str, str] = field(default_factory=dict)
    session: CrowdSession | None = None

    @property
    def preview(self) -> bool:
        return self.worker is None


class CrowdProvider(Protocol):
    name: ClassVar[str]

    def enter(self, args: dict[str, str]) -> Entry: ...

    def finish(self, context: dict[str, str]) -> dict[str, Any]:
        """What the page does when the worker is done: ``{"redirect": url}``, ``{"post": ...}`` or ``{}``."""
        ...


def _required(args: dict[str, str], *names: str) -> list[str]:
    values = [(args.get(name) or "").strip() for name in names]
    missing = [name for name, value in zip(names, values) if not value]
    if missing:
        raise TaskError(f"This link is missing {', '.join(missing)}; open it again from the study page")
    too_long = [name for name, value in zip(names, values) if len(value) > 190]
    if too_long:
        raise TaskError(f"Expected {', '.join(too_long)} of at most 190 characters")
    return values


class InviteProvider:
    name: ClassVar[str] = "invite"

    def enter(self, args: dict[str, str]) -> Entry:
        token = args.get("token", "")
        worker = db.session.scalar(select(Worker).where(Worker.provider == "invite", Worker.token == token))
        if worker is None:
            raise TaskError("This invite link is not valid; ask for a new one", 404)
        refusal = invite_statuses([worker.id])[worker.id].refusal()
        if refusal is not None:
            raise TaskError(refusal, 410)
        return Entry(self.name, worker, session=invite_session(worker))

    def finish(self, context: dict[str, str]) -> dict[str, Any]:
        return {}

    @staticmethod
    def invite(name: str) -> Worker:
        """A new in-house annotator; their link is ``/crowd/invite/<token>``."""
        existing = db.session.scalar(select(Worker).where(Worker.provider == "invite", Worker.external_id == name))
        if existing is not None:
            raise TaskError(f"An annotator called {name!r} is already invited", 409)
        worker = get_or_create_worker("invite", name)
        return worker


class ProlificProvider:
    name: ClassVar[str] = "prolific"

    def enter(self, args: dict[str, str]) -> Entry:
        pid, study, session_key = _required(args, "PROLIFIC_PID", "STUDY_ID", "SESSION_ID")
        session = open_session(self.name, pid, session_key, study)
        refuse_finished(session)
        return Entry(self.name, session.worker, {"study": study, "session": session_key}, session)

    def finish(self, context: dict[str, str]) -> dict[str, Any]:
        code = current_app.config.get("KEYSTONE_PROLIFIC_COMPLETION_CODE")
        if not code:
            raise TaskError("The study has no completion code configured; tell the researcher", 503)
        return {"redirect": f"{PROLIFIC_COMPLETION_URL}?{urlencode({'cc': code})}"}


def mturk_submit_url(turk_submit_to: str) -> str:
    """``turkSubmitTo + /mturk/externalSubmit``, only for MTurk's own hosts (no open form target)."""
    refused = TaskError(f"Expected turkSubmitTo on {' or '.join(MTURK_SUBMIT_ORIGINS)}, got {turk_submit_to!r}")
    try:
        parts = urlsplit(turk_submit_to.strip())
    except ValueError:  # no URL at all, e.g. "http://[::1" (an unclosed IPv6 host)
        raise refused from None
    origin = f"{parts.scheme}://{parts.netloc}"
    if origin not in MTURK_SUBMIT_ORIGINS or parts.query or parts.fragment or parts.path not in ("", "/"):
        raise refused
    return origin + "/mturk/externalSubmit"


class MTurkProvider:
    name: ClassVar[str] = "mturk"

    def enter(self, args: dict[str, str]) -> Entry:
        assignment = (args.get("assignmentId") or "").strip()
        if assignment == MTURK_PREVIEW_ASSIGNMENT:
            return Entry(self.name, None, {"assignment": assignment})
        assignment, hit, worker_id, submit_to = _required(args, "assignmentId", "hitId", "workerId", "turkSubmitTo")
        submit_url = mturk_submit_url(submit_to)
        session = open_session(self.name, worker_id, assignment, hit)
        refuse_finished(session)
        return Entry(self.name, session.worker, {"assignment": assignment, "hit": hit, "submit_url": submit_url}, session)

    def finish(self, context: dict[str, str]) -> dict[str, Any]:
        return {"post": {"url": context["submit_url"], "fields": {"assignmentId": context["assignment"]}}}


PROVIDERS: dict[str, CrowdProvider] = {p.name: p for p in (InviteProvider(), ProlificProvider(), MTurkProvider())}

FINISHED_SESSION = (
    "You finished this session and your answers are saved, so this page takes no more answers. "
    "To answer more, start a new session from the study page."
)


def refuse_finished(session: CrowdSession) -> None:
    """TaskError 410 when a Prolific or MTurk session is finished (an invite starts a new one instead)."""
    if session.completed_at is not None:
        raise TaskError(FINISHED_SESSION, 410)


# ---------------------------------------------------------------------------------------------
# The signed worker token


def _serializer() -> URLSafeSerializer:
    return URLSafeSerializer(current_app.config["SECRET_KEY"], salt=TOKEN_SALT)


def sign_entry(entry: Entry) -> str:
    """A token naming the worker, its session and the provider context; it authenticates every crowd API call.

    It includes a random nonce so two tabs of one worker get different tokens (nothing relies on
    that; it keeps tokens from being guessable from the worker id even if the key leaked partly).
    """
    assert entry.worker is not None and entry.session is not None
    return _serializer().dumps(
        {
            "w": entry.worker.id,
            "s": entry.session.id,
            "p": entry.provider,
            "c": entry.context,
            "n": secrets.token_hex(4),
            "t": int(_now()),  # signed at: the token expires token_lifetime_s() later
        }
    )


def _now() -> float:
    return time.time()


@dataclass(frozen=True)
class SignedWorker:
    """Who calls the crowd API: the signed token's claims and one read of the worker's row."""

    worker_id: int
    session_id: int
    provider: str
    context: dict[str, str]
    answered: int  # answers this session stored so far: the progress the page shows


_SESSION_STATE = (
    select(
        Worker.provider,
        CrowdSession.worker_id,
        select(func.count())
        .select_from(Answer)
        .where(Answer.worker_id == CrowdSession.worker_id, Answer.session_id == CrowdSession.id)
        .scalar_subquery(),
    )
    .add_columns(CrowdSession.completed_at)
    .join(Worker, Worker.id == CrowdSession.worker_id)
    .where(CrowdSession.id == bindparam("session_id"))
)


def load_signed_worker(token: str | None, *, finished_ok: bool = False) -> SignedWorker:
    """Check the token's signature, age, and that its session exists, of its worker, under its
    provider and not finished (one query, no ORM). ``finished_ok``: the finish page itself, which
    a participant may load again (its redirect failed, a reload).

    Runs on every API call, so it is one prebuilt statement: the ORM's identity-map load of
    the worker and a second count query cost as much as the rest of a fetch.
    """
    if not token:
        raise TaskError("Missing worker token: reload the task page", 403)
    try:
        data = _serializer().loads(token)
    except BadSignature as exc:
        raise TaskError("Invalid worker token: reload the task page", 403) from exc
    if not isinstance(data, dict) or "s" not in data or "t" not in data:
        # Tokens signed before sessions (or their lifetime) existed: the page must be opened again.
        raise TaskError("This task page is out of date: reload it", 403)
    lifetime = token_lifetime_s()
    if not isinstance(data["t"], int) or _now() - data["t"] > lifetime:
        raise TaskError(
            f"This task page was opened more than {lifetime / 3600:g} hours ago and has expired: open your link "
            "again to go on (your answers are saved)",
            401,
        )
    worker_id, session_id = int(data["w"]), int(data["s"])
    row = db.session.connection().execute(_SESSION_STATE, {"session_id": session_id}).first()
    if row is None or row.worker_id != worker_id or row.provider != data["p"]:
        raise TaskError("Unknown worker: reload the task page", 403)
    if row.completed_at is not None and not finished_ok:
        raise TaskError(
            "This session is finished, so it takes no more answers: open your link again to start a new one "
            "(your answers are saved)",
            410,
        )
    return SignedWorker(worker_id, session_id, data["p"], dict(data.get("c") or {}), int(row[2] or 0))
