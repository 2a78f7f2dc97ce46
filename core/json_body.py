"""The one loader for JSON request bodies: bounded in size, depth and numbers, 400 with a reason.

Python's ``json`` module accepts ``NaN`` and ``Infinity``, reads ``1e999`` as infinity, builds
integers of thousands of digits (which numpy, SQLite and PostgreSQL then refuse with an
OverflowError or a DataError) and recurses once per nesting level (``[`` * 100,000 is a
RecursionError). :func:`load_json_body` refuses all of those before the view sees the body:

- size: the request's body limit (:func:`core.limits.request_body_limit`), 413 above it;
- depth: at most :data:`MAX_DEPTH` nested arrays/objects (checked on the parsed document; one
  deeper than the C parser's recursion limit is refused as the RecursionError it raises);
- numbers: finite floats only, integers within +-2**53 (exact in a float and in JavaScript);
  NaN, Infinity and -Infinity are refused;
- text: no NUL characters and no lone surrogates (no database can store or compare them).

Browser forms (:class:`BrowserForm`) read form bodies only: Flask-WTF would otherwise feed them
``request.get_json()``, unbounded (a deeply nested array was a RecursionError, a 500) and with
objects where the fields expect text. A JSON body posted to one is a 415 that says so.

Views call it instead of ``request.get_json``; it raises :class:`JSONBodyError`, an HTTP 400
(415 for a body that is not JSON at all) that the app's error pages render as JSON for API
routes. Values the loader lets through still need their own checks (a box inside its card is
the annotation module's business, an id the database's range: :mod:`core.limits`).
"""

from __future__ import annotations

import json
import math
from typing import Any

from flask import request
from flask_wtf import FlaskForm
from werkzeug.exceptions import BadRequest, RequestEntityTooLarge, UnsupportedMediaType

from core.limits import request_body_limit

MAX_DEPTH = 32  # crowd answers nest 2 deep, review decisions 3
MAX_SAFE_INTEGER = 2**53


class JSONBodyError(BadRequest):
    """A JSON body that is malformed or out of bounds; the description says which and why."""


class NotJSONError(UnsupportedMediaType):
    description = "Expected a JSON body (Content-Type: application/json)."


class FormNotJSONError(UnsupportedMediaType):
    description = (
        "This form takes a form body (Content-Type: application/x-www-form-urlencoded or multipart/form-data), not JSON."
    )


class BrowserForm(FlaskForm):
    """A FlaskForm for pages people fill in: its data comes from the form body, never from JSON."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        # Only a form that reads the request (no formdata given): an error page re-rendering an
        # empty form (``formdata=None``) for a JSON request must still render.
        reads_the_body = not args and "formdata" not in kwargs
        if reads_the_body and request.is_json and request.method in ("POST", "PUT", "PATCH", "DELETE"):
            raise FormNotJSONError()
        super().__init__(*args, **kwargs)


def _refuse_constant(name: str) -> Any:
    raise JSONBodyError(f"Expected finite numbers in the JSON body, got {name}.")


def _bounded_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise JSONBodyError(f"Expected finite numbers in the JSON body, got {text[:40]} (out of range).")
    return value


def _bounded_int(text: str) -> int:
    # The length check comes first: int() of a 5,000-digit string is a ValueError, of a
    # 4,000-digit one a waste of time.
    if len(text.lstrip("-")) > len(str(MAX_SAFE_INTEGER)) or abs(value := int(text)) > MAX_SAFE_INTEGER:
        raise JSONBodyError(f"Expected whole numbers within +-2**53 in the JSON body, got one of {len(text.lstrip('-'))} digits.")
    return value


def parse_json(raw: bytes, *, max_depth: int = MAX_DEPTH) -> Any:
    """``raw`` JSON text as Python values, or :class:`JSONBodyError` saying what is wrong."""
    try:
        # UTF-8 only (RFC 8259 for JSON between systems); json.loads would also guess UTF-16/32.
        text = raw.decode("utf-8")
        document = json.loads(text, parse_constant=_refuse_constant, parse_float=_bounded_float, parse_int=_bounded_int)
    except JSONBodyError:
        raise
    except RecursionError:
        # The C parser recurses once per level and stops cleanly at the interpreter's limit
        # (about 1,000): far past max_depth, and long before a 64 KiB body of "[" ends.
        raise JSONBodyError(f"Expected JSON nested at most {max_depth} levels deep, got one nested too deep to parse.") from None
    except ValueError as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        if isinstance(exc, json.JSONDecodeError):
            reason = f"{exc.msg} at character {exc.pos}"
        elif isinstance(exc, UnicodeDecodeError):
            reason = "not UTF-8 text"
        else:
            reason = type(exc).__name__
        raise JSONBodyError(f"Expected a JSON body; this one is malformed ({reason}).") from None
    # Fast paths for ordinary bodies: a NUL or a surrogate can only come from a \\u escape (raw
    # control characters are invalid JSON, and UTF-8 cannot carry a surrogate), and a body with
    # at most max_depth brackets cannot nest deeper.
    check_text = "\\u" in text
    check_depth = text.count("[") + text.count("{") > max_depth
    if check_text or check_depth:
        check_document(document, max_depth=max_depth if check_depth else None, check_text=check_text)
    return document


def check_document(document: Any, *, max_depth: int | None = MAX_DEPTH, check_text: bool = True) -> None:
    """JSONBodyError for nesting deeper than ``max_depth`` (None: any depth), or (``check_text``)
    a NUL character or a lone surrogate in any string (keys included).

    Both are valid JSON escapes (``\\u0000``, ``\\ud800``) but no database stores them:
    PostgreSQL refuses NUL with a DataError, and a lone surrogate cannot be encoded as UTF-8 for
    SQLite or PostgreSQL (a UnicodeEncodeError).
    """
    visited = (dict, list, str) if check_text else (dict, list)
    pending: list[tuple[Any, int]] = [(document, 0)]  # iterative: no recursion to bound
    while pending:
        value, depth = pending.pop()
        if isinstance(value, str):
            if "\x00" in value:
                raise JSONBodyError("Text in the JSON body may not contain NUL characters (\\u0000).")
            if not value.isascii():
                try:
                    value.encode("utf-8")
                except UnicodeEncodeError:
                    raise JSONBodyError(
                        "Text in the JSON body may not contain lone surrogates (\\ud800-\\udfff without their pair)."
                    ) from None
        elif isinstance(value, (dict, list)):
            if max_depth is not None and depth + 1 > max_depth:
                raise JSONBodyError(f"Expected JSON nested at most {max_depth} levels deep, got deeper.")
            children = [*value.keys(), *value.values()] if isinstance(value, dict) else value
            pending.extend((child, depth + 1) for child in children if isinstance(child, visited))


def load_json_body(*, expect: type = dict, max_depth: int = MAX_DEPTH) -> Any:
    """The current request's JSON body, checked as described in the module docstring.

    ``expect`` is the type of the top-level value (a JSON object unless told otherwise).
    """
    if not request.is_json:
        raise NotJSONError()
    limit = request_body_limit()
    raw = request.get_data(cache=True)  # 413 past the limit (core.limits sets it per request)
    if limit is not None and len(raw) > limit:
        raise RequestEntityTooLarge(f"This request's body is {len(raw):,} bytes; the limit here is {limit:,} bytes.")
    body = parse_json(raw, max_depth=max_depth)
    if not isinstance(body, expect):
        names: dict[type, str] = {dict: "a JSON object", list: "a JSON array"}
        raise JSONBodyError(f"Expected {names.get(expect, expect.__name__)} body, got {type(body).__name__}.")
    return body
