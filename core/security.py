"""Security headers on every response, a per-view framing opt-in, and error pages without tracebacks.

Framing: every page may be framed only by this site (``frame-ancestors 'self'`` and, for old
browsers, ``X-Frame-Options: SAMEORIGIN``). A view that must be embedded elsewhere (the
MTurk ExternalQuestion page lives in an iframe on mturk.com) is decorated with
:func:`frameable_by`; its responses then name those origins in ``frame-ancestors`` and send no
``X-Frame-Options`` (which cannot express a list of origins; browsers that honour CSP ignore
it when ``frame-ancestors`` is present, the rest would block the frame). Such a page may also
submit its forms to those origins (MTurk's ``externalSubmit``), so they join ``form-action``.

A form posted after the session has expired (or with cookies lost) fails Flask-WTF's CSRF check
with "The CSRF session token is missing."; that one is answered as what it is, "Your session
expired: log in again", with a link to log in and come back to the page the form was on.

Redirects to a ``next`` page go only to a path on this site (:func:`safe_next`: no open
redirects); the login form and the expired-session page both use it.

Behind ``KEYSTONE_TRUSTED_PROXIES`` reverse proxies, Werkzeug's ProxyFix takes the client's
address and scheme from the headers those proxies set (never more hops than configured, so a
client cannot spoof its address by sending X-Forwarded-For itself).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any, TypeVar
from urllib.parse import urlsplit

from flask import Flask, Response, current_app, jsonify, render_template, request, url_for
from flask_wtf.csrf import CSRFError
from markupsafe import escape
from werkzeug.exceptions import BadRequest, HTTPException, InternalServerError
from werkzeug.middleware.proxy_fix import ProxyFix

F = TypeVar("F", bound=Callable[..., Any])

FRAME_ANCESTORS_ATTRIBUTE = "_keystone_frame_ancestors"

# Scripts only from our own origin: templates carry no inline script, so an injected
# <script> in a metadata field could not run even if escaping ever failed.
BASE_POLICY: tuple[tuple[str, str], ...] = (
    ("default-src", "'self'"),
    ("img-src", "'self' data: blob:"),
    ("style-src", "'self' 'unsafe-inline'"),
    ("script-src", "'self'"),
    ("object-src", "'none'"),
    ("base-uri", "'self'"),
)

ERROR_CODES = (400, 401, 403, 404, 405, 413, 500)  # the rest fall to the HTTPException handler

# A CSP source expression for a whole origin: 'self', or scheme://host[:port] with an
# optional leading "*." wildcard label. Anything else (paths, spaces, semicolons) could
# smuggle extra directives into the header.
_ORIGIN = re.compile(r"^(?:'self'|https?://(?:\*\.)?[A-Za-z0-9-]+(?:\.[A-Za-z0-9-]+)*(?::\d{1,5})?)$")


def content_security_policy(frame_ancestors: tuple[str, ...] = ("'self'",)) -> str:
    form_action = ["'self'", *(origin for origin in frame_ancestors if origin != "'self'")]
    directives = [
        *BASE_POLICY,
        ("form-action", " ".join(form_action)),
        ("frame-ancestors", " ".join(frame_ancestors)),
    ]
    return "; ".join(f"{name} {value}" for name, value in directives)


def frameable_by(*origins: str) -> Callable[[F], F]:
    """Let other sites frame this view: ``@frameable_by("'self'", "https://www.mturk.com")``.

    ``self`` (quoted or not) means this site. Origins are checked here, at import time, so a
    typo fails loudly instead of producing a header browsers ignore.
    """
    if not origins:
        raise ValueError("frameable_by needs at least one origin, e.g. 'self' or https://www.mturk.com")
    normalised = tuple("'self'" if origin in ("self", "'self'") else origin.rstrip("/") for origin in origins)
    for origin in normalised:
        if not _ORIGIN.match(origin):
            raise ValueError(f"Expected an origin like https://www.mturk.com or 'self', got {origin!r}")

    def decorate(view: F) -> F:
        setattr(view, FRAME_ANCESTORS_ATTRIBUTE, normalised)
        return view

    return decorate


def _frame_ancestors_of_current_view() -> tuple[str, ...] | None:
    if request.endpoint is None:
        return None
    view = current_app.view_functions.get(request.endpoint)
    return getattr(view, FRAME_ANCESTORS_ATTRIBUTE, None)


def set_security_headers(response: Response) -> Response:
    response.headers.setdefault("X-Content-Type-Options", "nosniff")
    response.headers.setdefault("Referrer-Policy", "same-origin")
    ancestors = _frame_ancestors_of_current_view()
    if ancestors is None:
        response.headers.setdefault("X-Frame-Options", "SAMEORIGIN")
        response.headers.setdefault("Content-Security-Policy", content_security_policy())
    else:
        response.headers.pop("X-Frame-Options", None)
        response.headers["Content-Security-Policy"] = content_security_policy(ancestors)
    return response


def safe_next(target: str | None) -> str | None:
    """``target`` if it is a path on this site, else None: no open redirects through ``next``."""
    if not target:
        return None
    target = target.strip()
    # Browsers treat a backslash like a slash, so "/\evil.com" would mean "//evil.com".
    if "\\" in target or any(ord(ch) < 32 for ch in target):
        return None
    try:
        parts = urlsplit(target)
    except ValueError:  # "http://[::1" and the like: not a URL, so not a place to send anyone
        return None
    if parts.scheme or parts.netloc or not target.startswith("/") or target.startswith("//"):
        return None
    return target


def prefers_json() -> bool:
    return request.accept_mimetypes.best_match(["text/html", "application/json"]) == "application/json"


def wants_json_error() -> bool:
    """JSON for the JSON API (its clients send ``Accept: */*``), for JSON requests, and on request."""
    return request.path.startswith("/crowd/api/") or request.is_json or prefers_json()


def render_error(error: HTTPException) -> tuple[Any, int]:
    code = error.code or 500
    name = error.name
    # A 5xx shows Werkzeug's generic sentence, never the exception text or a traceback.
    description = InternalServerError.description if code >= 500 else (error.description or name)
    if wants_json_error():
        response = jsonify({"error": {"code": code, "name": name, "message": description}})
    else:
        try:
            page = render_template("errors.html", code=code, name=name, description=description)
        except Exception:
            # The page itself failed (its layout reads the logged-in person from a database that
            # may be what is broken): log it and send a bare page rather than the server's own.
            current_app.logger.exception("The %s error page could not be rendered", code)
            page = f"<!doctype html><title>{code} {name}</title><h1>{code} {name}</h1><p>{escape(description)}</p>"
        response = Response(page)
    # Keep the headers an error carries, such as Allow on a 405 and WWW-Authenticate on a 401.
    for header, value in error.get_headers():
        if header.lower() != "content-type":
            response.headers[header] = value
    return response, code


# Flask-WTF's reason when the session holds no CSRF token: it expired, or cookies were lost.
CSRF_SESSION_MISSING = "The CSRF session token is missing."
SESSION_EXPIRED = "Your session expired: log in again."
STALE_FORM = "This form was opened before you logged in."


def page_to_return_to() -> str | None:
    """The page a failed form was on: the Referer when it is this site (browsers send it to the
    same origin under our Referrer-Policy), else this URL for a GET; None when unknown."""
    referrer = request.referrer
    if referrer:
        parts = urlsplit(referrer)
        if parts.netloc == request.host and parts.scheme in ("http", "https"):
            return safe_next(parts.path + (f"?{parts.query}" if parts.query else ""))
        return None
    return safe_next(request.full_path.rstrip("?")) if request.method == "GET" else None


def render_csrf_error(error: CSRFError) -> tuple[Any, int]:
    from flask_login import current_user

    if error.description != CSRF_SESSION_MISSING:
        return render_error(error)
    back = page_to_return_to()
    if current_user.is_authenticated:
        # Logging in starts a new session with a new token: a form opened before it is stale.
        return render_error(BadRequest(f"{STALE_FORM} (Reload {back or 'the page'} and submit it again.)"))
    login_path = url_for("auth.login")
    if back and urlsplit(back).path == login_path:
        login_url = back  # the login form itself: log in from a fresh copy of it, keeping its next
    else:
        login_url = url_for("auth.login", next=back) if back else login_path
    if prefers_json():
        body = {"error": {"code": 400, "name": "Session Expired", "message": SESSION_EXPIRED, "login_url": login_url}}
        return jsonify(body), 400
    return render_template("errors.html", code=400, name="Session expired", description=SESSION_EXPIRED, login_url=login_url), 400


def init_app(app: Flask) -> None:
    proxies = app.config.get("KEYSTONE_TRUSTED_PROXIES", 0)
    if proxies:
        app.wsgi_app = ProxyFix(app.wsgi_app, x_for=proxies, x_proto=proxies, x_host=0)  # type: ignore[method-assign]
    app.register_error_handler(CSRFError, render_csrf_error)
    app.after_request(set_security_headers)
    # Code-specific handlers win over the HTTPException one; Flask hands routing redirects
    # (308 for a missing slash) back untouched, and turns any unhandled exception into a
    # 500 that reaches this handler with nothing of the original shown (it is logged).
    for code in ERROR_CODES:
        app.register_error_handler(code, render_error)
    app.register_error_handler(HTTPException, render_error)
