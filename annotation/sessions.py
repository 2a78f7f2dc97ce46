"""Crowd sessions: one visit of a worker, and the limits on opening new ones.

A participant id in a Prolific or MTurk link is no secret (it travels in URLs, referrers,
screenshots), so it names a *worker* (for quality and for the N-answers-per-item rule) but
proves nothing. What a visit may touch (its reservations, the answers it may undo, its
progress, its completion) is bound to its *session*: Prolific's ``SESSION_ID``, MTurk's
``assignmentId``, or the invite link (one session per invited annotator). A session key is
bound to the participant that opened it first, so another participant id cannot reuse it.

Opening a new session is what an anonymous visitor can do in bulk, so it is limited per client
address and per study (``KEYSTONE_CROWD_SESSIONS_PER_ADDRESS``, ``KEYSTONE_CROWD_SESSIONS_PER_STUDY``
per ``KEYSTONE_CROWD_SESSION_WINDOW_S`` seconds); over a limit the entry page answers 429 with
Retry-After. Every new worker opens a new session, so this also limits worker creation. Reopening
a session the visitor already has is never limited. Only these entry pages check the limits:
the JSON API (fetch-next, submit, undo) runs no extra query for them. ``KEYSTONE_CROWD_STUDIES``
(a list, or a comma-separated string, of Prolific STUDY_IDs / MTurk hitIds) closes the entry
pages to any other study.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import math
import secrets
from datetime import UTC, datetime, timedelta

from flask import current_app, request
from sqlalchemy import func, select, text, update
from sqlalchemy.exc import IntegrityError

from core.db import db, utcnow

from .models import CrowdSession, Reservation, Worker
from .task_errors import TaskError

DEFAULT_SESSIONS_PER_ADDRESS = 20
DEFAULT_SESSIONS_PER_STUDY = 1000
DEFAULT_SESSION_WINDOW_S = 3600
# A new session from an address where a worker flagged on gold in the same study came from is
# refused work (see open_session); an operator whose participants share one address (a lab
# behind NAT) can turn this off.
DEFAULT_FLAG_SHARED_ADDRESS = True
INVITE_SESSION_PREFIX = "invite-worker-"


def client_network(remote_addr: str | None) -> str:
    """What the limits count as one client: the IPv4 address, or the IPv6 /64 network.

    One IPv6 subscriber usually holds a whole /64, so counting single IPv6 addresses would let
    them open sessions without limit.
    """
    try:
        address = ipaddress.ip_address(remote_addr or "")
    except ValueError:
        return remote_addr or "unknown"
    if isinstance(address, ipaddress.IPv6Address):
        if address.ipv4_mapped is not None:
            return str(address.ipv4_mapped)
        return str(ipaddress.IPv6Network((address, 64), strict=False))
    return str(address)


def client_address_key() -> str:
    """A keyed hash of the client's network (:func:`client_network`): enough to count and compare,
    never the address itself.

    The address is what the WSGI server reports (``request.remote_addr``); behind a reverse
    proxy that is the proxy's, unless the deployment rewrites it (werkzeug's ProxyFix).
    """
    key = str(current_app.config["SECRET_KEY"]).encode()
    network = client_network(request.remote_addr)
    return hmac.new(key, f"crowd-address:{network}".encode(), hashlib.sha256).hexdigest()[:32]


def check_study(study: str) -> None:
    """TaskError 404 unless ``study`` is one of ``KEYSTONE_CROWD_STUDIES`` (when that is set).

    STUDY_ID and hitId come from the URL, so without this list a visitor can name any study,
    and the per-study limit and flag inheritance are only as good as their honesty.
    """
    allowed = current_app.config.get("KEYSTONE_CROWD_STUDIES")
    if not allowed:
        return
    names = {name.strip() for name in allowed.split(",")} if isinstance(allowed, str) else {str(a) for a in allowed}
    if study not in names:
        raise TaskError("This study is not open here; open the link from the study page", 404)


def _as_utc(moment: datetime) -> datetime:
    # SQLite hands back naive datetimes for DateTime(timezone=True); they were stored as UTC.
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


def _limit(name: str, default: int) -> int:
    value = int(current_app.config.get(name, default))
    if value < 1:
        raise ValueError(f"Expected {name} >= 1, got {value}")
    return value


def _check_limit(where: object, limit: int, window: timedelta, now: datetime, what: str) -> None:
    count, oldest = db.session.execute(
        select(func.count(), func.min(CrowdSession.created_at)).where(where, CrowdSession.created_at > now - window)
    ).one()
    if count >= limit:
        retry = max(1, math.ceil((_as_utc(oldest) + window - now).total_seconds()))
        raise TaskError(
            f"Too many new sessions {what} ({count} in the last {int(window.total_seconds())} s); try again in {retry} s",
            429,
            retry_after=retry,
        )


def check_session_limits(provider: str, study: str, address: str, now: datetime) -> None:
    """TaskError 429 when opening one more session would pass the per-address or per-study limit."""
    window = timedelta(seconds=_limit("KEYSTONE_CROWD_SESSION_WINDOW_S", DEFAULT_SESSION_WINDOW_S))
    _check_limit(
        CrowdSession.address == address,
        _limit("KEYSTONE_CROWD_SESSIONS_PER_ADDRESS", DEFAULT_SESSIONS_PER_ADDRESS),
        window,
        now,
        "from your network address",
    )
    _check_limit(
        (CrowdSession.provider == provider) & (CrowdSession.study == study),
        _limit("KEYSTONE_CROWD_SESSIONS_PER_STUDY", DEFAULT_SESSIONS_PER_STUDY),
        window,
        now,
        "in this study",
    )


def _address_flagged_in_study(provider: str, study: str, address: str) -> bool:
    """Whether a worker flagged on gold opened a session of this study from this address."""
    if not current_app.config.get("KEYSTONE_CROWD_FLAG_SHARED_ADDRESS", DEFAULT_FLAG_SHARED_ADDRESS):
        return False
    return (
        db.session.scalar(
            select(CrowdSession.id)
            .join(Worker, Worker.id == CrowdSession.worker_id)
            .where(
                CrowdSession.provider == provider,
                CrowdSession.study == study,
                CrowdSession.address == address,
                Worker.flagged.is_(True),
            )
            .limit(1)
        )
        is not None
    )


def _existing(provider: str, participant: str, session_key: str, study: str) -> CrowdSession | None:
    """The session with this key, if it is this participant's in this study; 409 if it is not."""
    row = db.session.execute(
        select(CrowdSession, Worker.external_id)
        .join(Worker, Worker.id == CrowdSession.worker_id)
        .where(CrowdSession.provider == provider, CrowdSession.external_id == session_key)
    ).first()
    if row is None:
        return None
    session, owner = row
    if owner != participant:
        raise TaskError("This session was opened by another participant; open the study link you were given", 409)
    if session.study != study:
        raise TaskError("This session belongs to another study; open the study link you were given", 409)
    return session


def _serialize_openings(provider: str, study: str, address: str) -> None:
    """PostgreSQL: one opening at a time per address and per study, so the limits are exact.

    Transaction-scoped advisory locks, always address first, then study (no lock cycles).
    SQLite needs none: every write transaction there begins IMMEDIATE, one at a time.
    """
    if db.session.get_bind().dialect.name != "postgresql":
        return
    for key in (f"crowd-address:{address}", f"crowd-study:{provider}:{study}"):
        db.session.execute(text("SELECT pg_advisory_xact_lock(hashtext(:key))"), {"key": key})


def open_session(provider: str, participant: str, session_key: str, study: str, *, _retry: bool = True) -> CrowdSession:
    """The participant's session ``session_key``: the one they opened before, or a new one.

    A new one passes the creation limits first (429 over them), then finds or makes the worker,
    in the same write transaction as the check. It is refused work from the start (``flagged``)
    when a worker flagged on gold in the same study came from the same address: a spammer
    coming back under a new participant id.
    """
    check_study(study)
    existing = _existing(provider, participant, session_key, study)
    if existing is not None:
        return existing
    now = utcnow()
    address = client_address_key()
    _serialize_openings(provider, study, address)
    check_session_limits(provider, study, address, now)
    worker = db.session.scalar(select(Worker).where(Worker.provider == provider, Worker.external_id == participant))
    if worker is None:
        worker = Worker(provider=provider, external_id=participant, token=secrets.token_urlsafe(24))
        db.session.add(worker)
    session = CrowdSession(
        worker=worker,
        provider=provider,
        external_id=session_key,
        study=study,
        address=address,
        flagged=_address_flagged_in_study(provider, study, address),
        created_at=now,
    )
    db.session.add(session)
    try:
        db.session.commit()
    except IntegrityError:
        # The same session or the same new worker made twice at once: the first one wins; this
        # visit then reopens its session (or is refused, if it is another participant's).
        db.session.rollback()
        if not _retry:
            raise
        return open_session(provider, participant, session_key, study, _retry=False)
    return session


def invite_session(worker: Worker) -> CrowdSession:
    """An invited annotator's open session: their link is their credential, so every visit is it,
    until they finish it (``/crowd/finish``); the next visit then starts a new one.

    The first is ``invite-worker-<id>`` (the key migration 0005 gave existing annotators), later
    ones ``invite-worker-<id>-<n>``. Invites are made by staff (``keystone crowd invite``), so no
    limit applies.
    """
    first = f"{INVITE_SESSION_PREFIX}{worker.id}"
    mine = (CrowdSession.provider == "invite") & (CrowdSession.worker_id == worker.id)
    for _attempt in range(3):
        session = db.session.scalar(
            select(CrowdSession).where(mine, CrowdSession.completed_at.is_(None)).order_by(CrowdSession.id.desc()).limit(1)
        )
        if session is not None:
            return session
        made = db.session.scalar(select(func.count()).select_from(CrowdSession).where(mine)) or 0
        key = first if made == 0 else f"{first}-{made + 1}"
        session = CrowdSession(worker_id=worker.id, provider="invite", external_id=key, study="", address="", flagged=False)
        db.session.add(session)
        try:
            db.session.commit()
            return session
        except IntegrityError:
            # Two visits made it at once: the first one wins and this one reads it.
            db.session.rollback()
    raise TaskError("Could not open your session; reload the page", 503)


def complete_session(session_id: int) -> None:
    """Record the first time the session reached its provider's completion step (kept for payouts),
    and let its open holds lapse now: its token takes no more answers, so the cards it held go
    back to the pool at the next fetch (whose sweep releases and recounts them)."""
    session = db.session.get(CrowdSession, session_id)
    if session is not None and session.completed_at is None:
        now = utcnow()
        session.completed_at = now
        db.session.execute(
            update(Reservation)
            .where(
                Reservation.session_id == session_id,
                Reservation.answered_at.is_(None),
                Reservation.released_at.is_(None),
                Reservation.expires_at > now,
            )
            .values(expires_at=now)
        )
        db.session.commit()
