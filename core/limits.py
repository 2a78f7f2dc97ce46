"""Limits at the doors: request sizes, database ids in URLs and query strings.

Every value a request carries is bounded before it reaches the database or numpy, so hostile
input gets a 4xx that says what is allowed, never a 500:

- Bodies: ``MAX_CONTENT_LENGTH`` (1 MiB: the app takes no uploads; its largest forms are the
  release notes, 5,000 characters, and a review page's bulk selection) for every route, and
  ``KEYSTONE_API_MAX_BYTES`` (64 KiB: a crowd answer is under 200 bytes) under ``/crowd/api/``.
  A larger body is a 413 before anything reads it (when the client declares its length) or as
  soon as it is read past the limit (chunked bodies).
- Ids: every ``<int:...>`` in a route is :class:`DatabaseIdConverter`, registered in place of
  Werkzeug's ``int`` before any blueprint, so ``/cards/9223372036854775808`` is a 404 like any
  other missing card instead of an overflow in SQLite (64-bit) or PostgreSQL (``INTEGER`` is
  32-bit, and SQLAlchemy casts bound parameters to the column's type). Ids and numbers in query
  strings, forms and JSON bodies go through :func:`parse_whole_number` (ASCII digits only, in range).
- Text: no NUL characters in paths, query strings or forms (PostgreSQL cannot store them).
"""

from __future__ import annotations

import builtins
from typing import Any

import click
from flask import Flask, abort, current_app, request
from werkzeug.routing import IntegerConverter, Map, ValidationError

# The range both databases share: PostgreSQL INTEGER (and SERIAL ids) is 32-bit signed; SQLite
# is 64-bit. Ids start at 1 in both.
DATABASE_ID_MAX = 2**31 - 1
DATABASE_ID_DIGITS = len(str(DATABASE_ID_MAX))

DEFAULT_MAX_CONTENT_LENGTH = 1024 * 1024
DEFAULT_API_MAX_BYTES = 64 * 1024
API_PREFIX = "/crowd/api/"


class DatabaseIdConverter(IntegerConverter):
    """``<int:name>`` accepting only 1 .. 2**31 - 1; anything else does not match the route (404).

    Its length is checked before ``int()``: Python refuses to convert strings of more than
    4,300 digits (a ValueError Werkzeug would not catch) and a long one costs time for nothing.
    Explicit ``min``/``max`` arguments may narrow the range, never widen it.
    """

    # Werkzeug's pattern is \d+, which in Python matches any Unicode digit ("５", "٣").
    regex = r"[0-9]+"

    def __init__(
        self, map: Map, fixed_digits: int = 0, min: int | None = None, max: int | None = None, signed: bool = False
    ) -> None:
        if signed:
            raise ValueError("Database ids are never negative: use <int:...> without signed=True")
        super().__init__(
            map,
            fixed_digits=fixed_digits,
            min=builtins.max(1, min or 1),
            max=builtins.min(DATABASE_ID_MAX, max or DATABASE_ID_MAX),
        )

    def to_python(self, value: str) -> Any:
        try:
            number = parse_whole_number(value, "id", minimum=self.min or 1, maximum=self.max or DATABASE_ID_MAX)
        except ValueError:
            raise ValidationError() from None
        if self.fixed_digits and len(value) != self.fixed_digits:
            raise ValidationError()
        return number


def parse_whole_number(value: object, name: str, *, minimum: int = 1, maximum: int = DATABASE_ID_MAX) -> int:
    """``value`` (a URL part, query-string, form or JSON field called ``name``) as a whole number
    in ``minimum`` .. ``maximum``: the one strict reading of numbers at every door.

    Text must be ASCII digits only (surrounding whitespace aside): Python's ``int()`` also takes
    ``"1_0"`` (10), a fullwidth ``"５"``, Arabic-Indic ``"٣"`` and a sign, and ``str.isdigit`` is
    true for ``"²"``, which ``int()`` then refuses. A JSON integer is taken as it is (``True`` is
    not a number). The length is checked before ``int()``: Python refuses strings of more than
    4,300 digits with a ValueError, and a long one costs time for nothing.

    Raises ValueError with a sentence for the user (views turn it into a 400).
    """
    if isinstance(value, int) and not isinstance(value, bool):
        number: int | None = value
        shown = str(value)[:40] if value.bit_length() < 10_000 else "a number of thousands of digits"  # str() stops at 4,300
    elif isinstance(value, str):
        text = value.strip()
        shown = repr(text[:40])
        ascii_digits = text.isascii() and text.isdigit()
        number = int(text) if ascii_digits and len(text.lstrip("0")) <= len(str(maximum)) else None
    else:
        number, shown = None, type(value).__name__
    if number is None or not minimum <= number <= maximum:
        wanted = f"a positive whole number (at most {maximum})" if minimum == 1 else f"a whole number from {minimum} to {maximum}"
        raise ValueError(f"Expected {name} to be {wanted}, got {shown}.")
    return number


def parse_positive_int(value: object, name: str, *, maximum: int = DATABASE_ID_MAX) -> int:
    """``value`` as a database id or page number (1 .. ``maximum``); see :func:`parse_whole_number`."""
    return parse_whole_number(value, name, minimum=1, maximum=maximum)


class RecordIdType(click.ParamType):
    """A command-line id (a batch, a card): read by :func:`parse_whole_number`, as at the web's doors.

    click's ``type=int`` is Python's ``int()``: it takes ``1_0`` (10), a fullwidth ``５`` and ids
    past what the database holds, so ``keystone crowd export 1_0`` would export batch 10.
    """

    name = "record id"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> int:
        try:
            return parse_positive_int(value, "a record id")
        except ValueError:
            shown = repr(value[:40]) if isinstance(value, str) else repr(value)
            self.fail(f"Expected a record id (ASCII digits, 1 to {DATABASE_ID_MAX}), got {shown}.", param, ctx)


class RecordIdListType(click.ParamType):
    """Record ids separated by commas or spaces (``--cards 1,2,3``), each read as :class:`RecordIdType`."""

    name = "record ids"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> list[int]:
        if isinstance(value, list):
            return value
        return [RECORD_ID.convert(part, param, ctx) for part in str(value).replace(",", " ").split()]


RECORD_ID = RecordIdType()
RECORD_IDS = RecordIdListType()


def request_body_limit() -> int | None:
    """The byte limit for the current request's body: the API's where it applies, else the global one."""
    limit = current_app.config.get("MAX_CONTENT_LENGTH")
    if request.path.startswith(API_PREFIX):
        api_limit = int(current_app.config.get("KEYSTONE_API_MAX_BYTES", DEFAULT_API_MAX_BYTES))
        limit = api_limit if limit is None else min(limit, api_limit)
    return limit


def refuse_large_bodies() -> None:
    """Before any view (and before CSRF checks read a form): refuse a declared length over the limit.

    Setting ``request.max_content_length`` also makes Werkzeug stop reading a body that did not
    declare its length (chunked) once it passes the limit.
    """
    limit = request_body_limit()
    if limit is None:
        return
    request.max_content_length = limit
    if request.content_length is not None and request.content_length > limit:
        abort(413, f"This request's body is {request.content_length:,} bytes; the limit here is {limit:,} bytes.")


def refuse_nul_characters() -> None:
    """400 for a NUL character in the path, the query string or a form field.

    No field of this app may hold one, and PostgreSQL refuses any text containing one with a
    DataError, so a single ``%00`` in a login name or a filter would otherwise be a 500 there.
    (JSON bodies are checked by :func:`core.json_body.load_json_body`.)
    """
    fields = request.args.items(multi=True)
    if request.mimetype in ("application/x-www-form-urlencoded", "multipart/form-data"):
        fields = (*fields, *request.form.items(multi=True))
    if "\x00" in request.path or any("\x00" in name or "\x00" in value for name, value in fields):
        abort(400, "Text in a request may not contain NUL characters (%00).")


def init_app(app: Flask) -> None:
    """Call before any blueprint is registered (rules bind their converters when added)."""
    app.url_map.converters["int"] = DatabaseIdConverter
    # First in line, ahead of CSRFProtect's hook, which reads the form of every POST.
    app.before_request_funcs.setdefault(None, [])[:0] = [refuse_large_bodies, refuse_nul_characters]
