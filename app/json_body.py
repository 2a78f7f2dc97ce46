"""The one loader for JSON request bodies: bounded in size, depth and numbers, 400 with a reason.

Python's ``json`` module accepts ``NaN`` and ``Infinity``, reads ``1e999`` as infinity, builds
integers of thousands of digits (which numpy, SQLite and PostgreSQL then refuse with an
OverflowError or a DataError) and recurses once per nesting level (``[`` * 100,000 is a
RecursionError). :func:`load_json_body` refuses all of those before the view sees the body:

- size: the request's body limit (:func:`app.limits.request_body_limit`), 413 above it;
- depth: at most :data:`MAX_DEPTH` nested arrays/objects, counted on the raw text before parsing;
- numbers: finite floats only, integers within +-2**53 (exact in a float and in JavaScript);
  NaN, Infinity and -Infinity are refused;
- text: no NUL characters and no lone surrogates (no database can store or compare them).

Views call it instead of ``request.get_json``; it raises :class:`JSONBodyError`, an HTTP 400
(415 for a body that is not JSON at all) that the app's error pages render as JSON for API
routes. Values the loader lets through still need their own checks (a box inside its card is
the annotation module's business, an id the database's range: :mod:`app.limits`).
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

from flask import request
from werkzeug.exceptions import BadRequest, RequestEntityTooLarge, UnsupportedMediaType

from .limits import request_body_limit

MAX_DEPTH = 32  # crowd answers nest 2 deep, review decisions 3
MAX_SAFE_INTEGER = 2**53
# A JSON string (with escapes) or any character that opens or closes a container.
_STRING_OR_BRACKET = re.compile(rb'"(?:[^"\\]|\\.)*"|[\[\]{}]', re.DOTALL)


class JSONBodyError(BadRequest):
    """A JSON body that is malformed or out of bounds; the description says which and why."""


class NotJSONError(UnsupportedMediaType):
    description = "Expected a JSON body (Content-Type: application/json)."


def nesting_depth(raw: bytes) -> int:
    """The deepest nesting of arrays and objects in ``raw`` JSON text, brackets inside strings ignored."""
    depth = deepest = 0
    for match in _STRING_OR_BRACKET.finditer(raw):
        token = match.group()
        if token in (b"[", b"{"):
            depth += 1
            deepest = max(deepest, depth)
        elif token in (b"]", b"}"):
            depth -= 1
    return deepest


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
        raise JSONBodyError(f"Expected whole numbers within +-2**53 in the JSON body, "
                            f"got one of {len(text.lstrip('-'))} digits.")
    return value


def parse_json(raw: bytes, *, max_depth: int = MAX_DEPTH) -> Any:
    """``raw`` JSON text as Python values, or :class:`JSONBodyError` saying what is wrong."""
    # Counting every bracket is cheap next to parsing; a body with few is shallow enough already.
    depth = nesting_depth(raw) if raw.count(b"[") + raw.count(b"{") > max_depth else 0
    if depth > max_depth:
        raise JSONBodyError(f"Expected JSON nested at most {max_depth} levels deep, got {depth}.")
    try:
        return json.loads(raw, parse_constant=_refuse_constant, parse_float=_bounded_float, parse_int=_bounded_int)
    except JSONBodyError:
        raise
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        if isinstance(exc, json.JSONDecodeError):
            reason = f"{exc.msg} at character {exc.pos}"
        elif isinstance(exc, UnicodeDecodeError):
            reason = "not UTF-8 text"
        else:
            reason = type(exc).__name__
        raise JSONBodyError(f"Expected a JSON body; this one is malformed ({reason}).") from None


def _refuse_unstorable_text(document: Any) -> None:
    """JSONBodyError for a NUL character or a lone surrogate in any string (keys included).

    Both are valid JSON escapes (``\\u0000``, ``\\ud800``) but no database stores them:
    PostgreSQL refuses NUL with a DataError, and a lone surrogate cannot be encoded as UTF-8 for
    SQLite or PostgreSQL (a UnicodeEncodeError).
    """
    # Iterative: the depth is bounded already, but a walk without recursion needs no bound at all.
    pending = [document]
    while pending:
        value = pending.pop()
        if isinstance(value, str):
            if "\x00" in value:
                raise JSONBodyError("Text in the JSON body may not contain NUL characters (\\u0000).")
            if not value.isascii():
                try:
                    value.encode("utf-8")
                except UnicodeEncodeError:
                    raise JSONBodyError("Text in the JSON body may not contain lone surrogates "
                                        "(\\ud800-\\udfff without their pair).") from None
        elif isinstance(value, dict):
            pending.extend(value.keys())
            pending.extend(value.values())
        elif isinstance(value, list):
            pending.extend(value)


def load_json_body(*, expect: type = dict, max_depth: int = MAX_DEPTH) -> Any:
    """The current request's JSON body, checked as described in the module docstring.

    ``expect`` is the type of the top-level value (a JSON object unless told otherwise).
    """
    if not request.is_json:
        raise NotJSONError()
    limit = request_body_limit()
    raw = request.get_data(cache=True)  # 413 past the limit (app.limits sets it per request)
    if limit is not None and len(raw) > limit:
        raise RequestEntityTooLarge(f"This request's body is {len(raw):,} bytes; the limit here is {limit:,} bytes.")
    body = parse_json(raw, max_depth=max_depth)
    _refuse_unstorable_text(body)
    if not isinstance(body, expect):
        names = {dict: "a JSON object", list: "a JSON array"}
        raise JSONBodyError(f"Expected {names.get(expect, expect.__name__)} body, got {type(body).__name__}.")
    return body
