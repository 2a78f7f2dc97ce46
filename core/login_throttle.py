"""Login throttling: how many wrong passwords an account, and a client address, may cost per window.

Budgets (``KEYSTONE_LOGIN_FAILURES_PER_ACCOUNT``, ``..._PER_ADDRESS``) count wrong passwords in a
fixed window (``KEYSTONE_LOGIN_WINDOW_MINUTES``) that starts at the first one. Once a budget is
spent, every attempt on that account (or from that address) is refused, the right password
included, until the window ends; the refusal says when (``Retry-After``). Attempts refused that
way cost nothing, so a locked-out person who keeps trying does not lock themselves out longer.

An attempt is counted *before* its password is checked: it reserves one failure against both
budgets in a short write transaction (rows locked ``FOR UPDATE`` on PostgreSQL; on SQLite every
write transaction begins IMMEDIATE, one at a time), and a right password gives the reservation
back. So concurrent guesses cannot all pass a check that none of them has been counted against
yet: with a budget of 5, a sixth guess is refused while the first five are still being hashed.
The counts live in the database (``login_throttles``), shared by every server process.

A right password resets the account's count (earlier misses were typos) but only gives back its
own reservation on the address (one valid account must not let an address go on guessing at
others). Unknown usernames are counted like real ones: the answers do not tell them apart.
"""

from __future__ import annotations

import ipaddress
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

from flask import current_app, request
from sqlalchemy import delete, select, tuple_
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from core.db import db, utcnow
from core.models import THROTTLE_SCOPES, LoginThrottle

# Addresses are kept to this length (IPv6 with a zone is the longest plausible form).
ADDRESS_LENGTH = 64
# An IPv6 host gets a whole /64 from its provider: throttling single addresses would give an
# attacker 2**64 budgets.
IPV6_PREFIX = 64


@dataclass(frozen=True)
class ThrottlePolicy:
    window: timedelta
    per_account: int  # wrong passwords per account per window
    per_address: int  # wrong passwords per client address per window

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> ThrottlePolicy:
        return cls(
            window=config["KEYSTONE_LOGIN_WINDOW"],
            per_account=config["KEYSTONE_LOGIN_FAILURES_PER_ACCOUNT"],
            per_address=config["KEYSTONE_LOGIN_FAILURES_PER_ADDRESS"],
        )

    def budget(self, scope: str) -> int:
        if scope not in THROTTLE_SCOPES:
            raise ValueError(f"Expected a scope from {', '.join(THROTTLE_SCOPES)}, got {scope!r}")
        return self.per_account if scope == "account" else self.per_address


@dataclass(frozen=True)
class Lockout:
    """Why an attempt was refused: which budget is spent, and for how long still."""

    scope: str  # "account" or "address"
    retry_after_s: int  # whole seconds until the window ends, at least 1
    failures: int  # counted in the window

    @property
    def minutes(self) -> int:
        return max(1, math.ceil(self.retry_after_s / 60))


def as_utc(moment: datetime) -> datetime:
    # SQLite hands timezone-aware columns back naive; they were stored in UTC.
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


def counted_failures(failures: int, window_started_at: datetime, now: datetime, window: timedelta) -> int:
    """The failures that still count at ``now``: none once the window has ended."""
    return failures if now < as_utc(window_started_at) + window else 0


def lockout_of(scope: str, failures: int, window_started_at: datetime, now: datetime, policy: ThrottlePolicy) -> Lockout | None:
    """The lockout a throttle row imposes at ``now``, or None while its budget lasts."""
    counted = counted_failures(failures, window_started_at, now, policy.window)
    if counted < policy.budget(scope):
        return None
    remaining = (as_utc(window_started_at) + policy.window - now).total_seconds()
    return Lockout(scope=scope, retry_after_s=max(1, math.ceil(remaining)), failures=counted)


def clock() -> datetime:
    """Now, in UTC; ``KEYSTONE_CLOCK`` (a callable, for tests) replaces the wall clock."""
    now: Callable[[], datetime] = current_app.config.get("KEYSTONE_CLOCK") or utcnow
    return now()


def normalise_address(address: str | None) -> str:
    """The key an address is throttled under: IPv4 as is, IPv6 as its /64 network."""
    if not address:
        return "unknown"
    try:
        parsed = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return address[:ADDRESS_LENGTH]
    if isinstance(parsed, ipaddress.IPv6Address):
        if parsed.ipv4_mapped is not None:
            return str(parsed.ipv4_mapped)
        return str(ipaddress.ip_network(f"{parsed}/{IPV6_PREFIX}", strict=False))
    return str(parsed)


def client_address() -> str:
    """This request's client, as throttled. Behind proxies, ``KEYSTONE_TRUSTED_PROXIES`` makes
    ``remote_addr`` the client's (core.security applies Werkzeug's ProxyFix)."""
    return normalise_address(request.remote_addr)


def _keys(username: str, address: str) -> list[tuple[str, str]]:
    # Sorted, so two transactions lock the same rows in the same order and cannot deadlock.
    # Usernames are unique ignoring case and log-in finds them ignoring case, so "Admin" and
    # "ADMIN" are guesses against one account and count against one budget.
    return sorted([("account", username.lower()[:120]), ("address", address)])


def _locked_rows(session: Session, keys: list[tuple[str, str]], now: datetime) -> list[LoginThrottle]:
    insert = postgresql.insert if session.get_bind().dialect.name == "postgresql" else sqlite.insert
    session.execute(
        insert(LoginThrottle)
        .values([{"scope": scope, "subject": subject, "window_started_at": now, "failures": 0} for scope, subject in keys])
        .on_conflict_do_nothing()
    )
    rows = []
    for scope, subject in keys:
        rows.append(
            session.execute(
                select(LoginThrottle)
                .where(LoginThrottle.scope == scope, LoginThrottle.subject == subject)
                .with_for_update()
                .execution_options(populate_existing=True)
            ).scalar_one()
        )
    return rows


def reserve_attempt(
    username: str, address: str, policy: ThrottlePolicy, now: datetime, session: Session | None = None
) -> Lockout | None:
    """Count one attempt against the account's and the address's budgets, or say which is spent.

    Runs in the caller's write transaction (begin it with :func:`core.db.one_writer`, commit it
    after). When a budget is spent nothing is counted and the longer lockout is returned.
    """
    session = session or db.session()
    rows = _locked_rows(session, _keys(username, address), now)
    lockouts = [lockout for row in rows if (lockout := lockout_of(row.scope, row.failures, row.window_started_at, now, policy))]
    if lockouts:
        return max(lockouts, key=lambda lockout: lockout.retry_after_s)
    for row in rows:
        if counted_failures(row.failures, row.window_started_at, now, policy.window) == 0:
            row.window_started_at, row.failures = now, 0
        row.failures += 1
    return None


def give_back_attempt(username: str, address: str, policy: ThrottlePolicy, now: datetime, session: Session | None = None) -> None:
    """The password was right: clear the account's count and return the address's reservation.

    Also drops rows whose window has ended (rows that others hold locked are left for later), so
    the table holds only names and addresses tried in the last window. Runs in the caller's write
    transaction.
    """
    session = session or db.session()
    keys = _keys(username, address)
    for row in _locked_rows(session, keys, now):
        row.failures = 0 if row.scope == "account" else max(0, row.failures - 1)
    ended = (
        select(LoginThrottle.scope, LoginThrottle.subject)
        .where(LoginThrottle.window_started_at <= now - policy.window)
        .with_for_update(skip_locked=True)
    )
    stale = [(scope, subject) for scope, subject in session.execute(ended) if (scope, subject) not in keys]
    if stale:
        session.execute(delete(LoginThrottle).where(tuple_(LoginThrottle.scope, LoginThrottle.subject).in_(stale)))
