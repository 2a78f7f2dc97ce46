"""Security headers on every response, a per-view framing opt-in, and error pages without tracebacks.

Framing: every page may be framed only by this site (``frame-ancestors 'self'`` and, for old
browsers, ``X-Frame-Options: SAMEORIGIN``). A view that must be embedded elsewhere (the
MTurk ExternalQuestion page lives in an iframe on mturk.com) is decorated with
:func:`frameable_by`; its responses then name those origins in ``frame-ancestors`` and send no
``X-Frame-Options`` (which cannot express a list of origins; browsers that honour CSP ignore
it when ``frame-ancestors`` is present, the rest would block the frame). Such a page may also
submit its forms to those origins (MTurk's ``externalSubmit``), so they join ``form-action``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any, TypeVar

from flask import Flask, Response, current_app, jsonify, render_template, request
from markupsafe import escape
from werkzeug.exceptions import HTTPException, InternalServerError

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


def init_app(app: Flask) -> None:
    app.after_request(set_security_headers)
    # Code-specific handlers win over the HTTPException one; Flask hands routing redirects
    # (308 for a missing slash) back untouched, and turns any unhandled exception into a
    # 500 that reaches this handler with nothing of the original shown (it is logged).
    for code in ERROR_CODES:
        app.register_error_handler(code, render_error)
    app.register_error_handler(HTTPException, render_error)
