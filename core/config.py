"""Configuration: defaults, then environment variables (``KEYSTONE_*``), then a test mapping.

``KEYSTONE_DATABASE_URL``  SQLAlchemy URL; default ``sqlite:///<instance>/keystone.sqlite3``.
``KEYSTONE_DATA_DIR``      originals store and derived artifacts; default ``<instance>/data``.
``KEYSTONE_SECRET_KEY``    session signing key; default a random key persisted in the instance folder.
``KEYSTONE_MAX_PIXELS``    decode cap per image (decompression-bomb guard); default 150 MP.
``KEYSTONE_INSTANCE_PATH`` where the instance folder lives; default Flask's.
``KEYSTONE_RELEASES_DIR``   where releases published from the web go; default ``<data dir>/releases``.
``KEYSTONE_MAX_REQUEST_BYTES`` the largest request body any route accepts (413 above it); default 1 MiB.
``KEYSTONE_API_MAX_BYTES``  the same for the crowd JSON API under ``/crowd/api/``; default 64 KiB.
``KEYSTONE_INPAINT_CHECKPOINT`` a ``keystone train-inpainting`` checkpoint the views stage fills
                          holes with; default none (OpenCV Telea fills them).
``KEYSTONE_SESSION_HOURS``  how long a login lasts, from the moment of logging in; default 8 (a
                          working day). Logging out ends a session at once, on the server.
``KEYSTONE_SECURE_COOKIES`` ``1`` behind HTTPS: the session cookie is then sent only over TLS.
``KEYSTONE_TRUSTED_PROXIES`` how many reverse proxies in front of the app append to
                          X-Forwarded-For (and set X-Forwarded-Proto); default 0: the peer's
                          address is the client's. Login throttling counts per client address.
``KEYSTONE_LOGIN_WINDOW_MINUTES``        the login throttle's window; default 15.
``KEYSTONE_LOGIN_FAILURES_PER_ACCOUNT``  wrong passwords per account per window; default 5.
``KEYSTONE_LOGIN_FAILURES_PER_ADDRESS``  wrong passwords per client address per window (an office
                          behind one address shares it); default 30.
"""

from __future__ import annotations

import math
import os
import secrets
from collections.abc import Mapping
from datetime import timedelta
from pathlib import Path
from typing import Any

from core.limits import DEFAULT_API_MAX_BYTES, DEFAULT_MAX_CONTENT_LENGTH
from pipeline.io import DEFAULT_MAX_PIXELS


def _persistent_secret(instance_path: Path) -> str:
    # A random key written once keeps logins valid across restarts without asking the
    # operator to invent one; an explicit KEYSTONE_SECRET_KEY always wins.
    key_file = instance_path / "secret_key"
    if key_file.exists():
        return key_file.read_text().strip()
    instance_path.mkdir(parents=True, exist_ok=True)
    key = secrets.token_hex(32)
    fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.write(key)
    return key


def normalise_database_url(url: str) -> str:
    """Use the psycopg 3 driver for plain ``postgresql://`` / ``postgres://`` URLs.

    SQLAlchemy would otherwise pick psycopg2, which Keystone does not install.
    """
    for prefix in ("postgresql://", "postgres://"):
        if url.startswith(prefix):
            return "postgresql+psycopg://" + url[len(prefix) :]
    return url


def _positive_number(env: Mapping[str, str], name: str, default: float) -> float:
    raw = env.get(name)
    if raw is None or raw.strip() == "":
        return default
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"Expected {name} to be a positive number, got {raw!r}")
    return value


def _count(env: Mapping[str, str], name: str, default: int, *, allow_zero: bool = False) -> int:
    raw = env.get(name)
    if raw is None or raw.strip() == "":
        return default
    try:
        value = int(raw)
    except ValueError:
        value = -1
    if value < 0 or (value == 0 and not allow_zero):
        kind = "a whole number >= 0" if allow_zero else "a positive whole number"
        raise ValueError(f"Expected {name} to be {kind}, got {raw!r}")
    return value


def config_from_environment(instance_path: str) -> dict[str, Any]:
    instance = Path(instance_path)
    env = os.environ
    secure_cookies = env.get("KEYSTONE_SECURE_COOKIES", "0").strip().lower() in ("1", "true", "yes", "on")
    database_url = normalise_database_url(env.get("KEYSTONE_DATABASE_URL") or f"sqlite:///{instance / 'keystone.sqlite3'}")
    return {
        "SQLALCHEMY_DATABASE_URI": database_url,
        "KEYSTONE_DATA_DIR": env.get("KEYSTONE_DATA_DIR") or str(instance / "data"),
        "SECRET_KEY": env.get("KEYSTONE_SECRET_KEY") or _persistent_secret(instance),
        "KEYSTONE_MAX_PIXELS": int(env.get("KEYSTONE_MAX_PIXELS", DEFAULT_MAX_PIXELS)),
        # Flask's default is 31 days; the signed cookie is refused past this age, and the
        # login time kept in the session ends it this long after logging in (core.auth).
        "PERMANENT_SESSION_LIFETIME": timedelta(hours=_positive_number(env, "KEYSTONE_SESSION_HOURS", 8)),
        # Flask's name for the body limit of every request (core/limits.py answers 413 above it).
        "MAX_CONTENT_LENGTH": int(env.get("KEYSTONE_MAX_REQUEST_BYTES", DEFAULT_MAX_CONTENT_LENGTH)),
        "KEYSTONE_API_MAX_BYTES": int(env.get("KEYSTONE_API_MAX_BYTES", DEFAULT_API_MAX_BYTES)),
        "SESSION_COOKIE_HTTPONLY": True,
        "SESSION_COOKIE_SAMESITE": "Lax",
        # Secure cookies need HTTPS; `keystone serve` on loopback is plain HTTP, so the
        # operator turns this on behind TLS (KEYSTONE_SECURE_COOKIES=1).
        "SESSION_COOKIE_SECURE": secure_cookies,
        "REMEMBER_COOKIE_HTTPONLY": True,
        "REMEMBER_COOKIE_SECURE": secure_cookies,
        "KEYSTONE_TRUSTED_PROXIES": _count(env, "KEYSTONE_TRUSTED_PROXIES", 0, allow_zero=True),
        "KEYSTONE_LOGIN_WINDOW": timedelta(minutes=_positive_number(env, "KEYSTONE_LOGIN_WINDOW_MINUTES", 15)),
        "KEYSTONE_LOGIN_FAILURES_PER_ACCOUNT": _count(env, "KEYSTONE_LOGIN_FAILURES_PER_ACCOUNT", 5),
        "KEYSTONE_LOGIN_FAILURES_PER_ADDRESS": _count(env, "KEYSTONE_LOGIN_FAILURES_PER_ADDRESS", 30),
        "WTF_CSRF_TIME_LIMIT": None,
        "CATALOG_PAGE_SIZE": 48,
        "KEYSTONE_INPAINT_CHECKPOINT": env.get("KEYSTONE_INPAINT_CHECKPOINT") or None,
        "KEYSTONE_RELEASES_DIR": env.get("KEYSTONE_RELEASES_DIR") or None,
        # A release page's Verify runs `keystone verify` in a child process stopped after this.
        "KEYSTONE_VERIFY_TIMEOUT_S": _positive_number(env, "KEYSTONE_VERIFY_TIMEOUT_S", 60),
    }
