"""The crowd's questions: one table that the pages, their scripts, validation, aggregation, the
simulated crowd and the curators' pages all read.

Two task kinds ask yes/no questions about a card:

* the judge task (:data:`JUDGE`), one card at a time: each question is a control on
  ``annotation/judge.html`` that a key toggles; its answer is stored under the question's key;
* the confirm grid (:data:`GRID`), 24-48 cards at once: each question is a tap on a card that
  looks wrong; the answer is ``{key: tapped}`` and what it says about the card is ``shown XOR
  tapped`` (:mod:`annotation.confirm`). The grid's keys are the orientation flags of
  :mod:`pipeline.decided_orientation` (``upside_down``, ``inverted``, ``swapped``), which the grid's pictures
  apply (:mod:`annotation.grid_pictures`): a grid question other than those needs a picture that
  shows it, and is not a table row alone.

Stored answers, ``answers.csv`` and the aggregates keep each question's ``key`` as the field
name, so a key never changes once answers exist. Every reader looks the table up when it runs
(:func:`judge_questions`, :func:`grid_questions`), never at import, so a test can add a row.
Pure: no Flask, no SQLAlchemy.

How to add a judge question: docs/ARCHITECTURE.md, "How to add ... a crowd question".
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

__all__ = [
    "GRID",
    "GRID_RESERVED_KEYS",
    "JUDGE",
    "JUDGE_RESERVED_KEYS",
    "Question",
    "asked",
    "check_table",
    "grid_questions",
    "judge_questions",
    "keys",
    "page_table",
    "required_keys",
]

# The kinds of answer a question may have, and how each is aggregated. Every question so far is
# yes/no (stored as a JSON boolean) aggregated by one binary Dawid-Skene of its own
# (:func:`annotation.aggregation.aggregate_judgements`, :func:`annotation.confirm.aggregate_taps`).
AnswerType = Literal["yes_no"]
Aggregation = Literal["dawid_skene"]
ANSWER_TYPES: tuple[str, ...] = ("yes_no",)
AGGREGATIONS: tuple[str, ...] = ("dawid_skene",)
# The widgets a page can draw a question as; a new one is a macro in
# ``annotation/templates/annotation/_questions.html`` (and, if it needs any, its script).
WIDGETS: dict[str, tuple[str, ...]] = {"judge": ("checkbox", "eye_order"), "grid": ("tap",)}

# Keys the pages already use for something else (Enter submits everywhere).
JUDGE_RESERVED_KEYS: frozenset[str] = frozenset({"u", "h", "?"})  # undo, help
GRID_RESERVED_KEYS: frozenset[str] = frozenset({"h", "?"})  # help; arrows move between cards


@dataclass(frozen=True)
class Question:
    """One yes/no question of a crowd task.

    ``default`` is the answer a worker gives by leaving the control alone; ticking the box (or
    tapping the card) gives the other one. That is how "Not a stereo pair" (key ``is_stereo``,
    default yes) reads as a box to tick only on the rare card.
    """

    key: str  # the field in stored answers, answers.csv, gold and aggregate labels: never renamed
    name: str  # short name: the help's list, the key hints, titles ("Upside-down")
    label: str  # what the control itself says (the checkbox's text, the tap button's text)
    hotkey: str  # one lower-case key that toggles it on its page
    help: str  # the help dialog's line after the name: what to look for
    review: str  # how a curator reads it: "Is it {review}?", "{review}: 25 % likely"
    default: bool = False  # the answer of an untouched control
    optional: bool = False  # older pages did not ask it: absent there, aggregated over the answers that have it
    gate: bool = False  # a "no" here makes the other questions moot (no orientation without a stereo pair)
    widget: str = "checkbox"
    answer: AnswerType = "yes_no"
    aggregate: Aggregation = "dawid_skene"

    def as_json(self) -> dict[str, Any]:
        """What a page's script needs: the key, the hotkey, the untouched answer, the widget."""
        return {"key": self.key, "hotkey": self.hotkey, "default": self.default, "widget": self.widget}


JUDGE: tuple[Question, ...] = (
    Question(
        key="is_stereo",
        name="Not a stereo pair",
        label="Not a stereo pair",
        hotkey="n",
        help="a single photo, a card back, text only, or two different pictures.",
        review="a stereo pair",
        default=True,
        gate=True,
    ),
    Question(
        key="upside_down",
        name="Upside-down",
        label="Upside-down",
        hotkey="f",
        help="the sky is at the bottom, writing reads upside-down.",
        review="upside down",
    ),
    Question(
        key="inverted",
        name="Inverted",
        label="Inverted (negative)",
        hotkey="i",
        help="it looks like a film negative: dark skies, white shadows.",
        review="a negative (inverted)",
    ),
    Question(
        key="swapped",
        name="Photos in the wrong order",
        label='Near is warm only in "Photos exchanged": the photos are in the wrong order',
        hotkey="s",
        help=(
            "under the card, two pictures colour the depth read from the two photos, near warm (red, yellow) "
            "and far cool (blue): once as scanned, once with the photos exchanged. Tap the one where near "
            'things (often the ground at the bottom) are warm; when that is "Photos exchanged", the photos '
            "are in the wrong order."
        ),
        review="in the wrong eye order (photos exchanged)",
        optional=True,
        widget="eye_order",
    ),
)

GRID: tuple[Question, ...] = (
    Question(
        key="upside_down",
        name="Upside down",
        label="Upside down",
        hotkey="u",
        help="the sky is at the bottom, people stand on their heads.",
        review="upside down",
        widget="tap",
    ),
    Question(
        key="inverted",
        name="Negative",
        label="Negative",
        hotkey="n",
        help="it looks like a film negative: dark skies, white shadows.",
        review="a negative (inverted)",
        widget="tap",
    ),
    Question(
        key="swapped",
        name="Depth inside out",
        label="Inside out",
        hotkey="d",
        help="in the strip, the near ground is blue and the sky or the distance is red or yellow.",
        review="in the wrong eye order (photos exchanged)",
        widget="tap",
    ),
)


def check_table(questions: Sequence[Question], page: str, reserved: Iterable[str] = ()) -> None:
    """ValueError unless ``questions`` can share one page: distinct keys and hotkeys, hotkeys that
    are one lower-case letter the page does not use already, known widgets, answer types and
    aggregations."""
    seen_keys: set[str] = set()
    seen_hotkeys: set[str] = set(reserved)
    for q in questions:
        if not q.key.isidentifier() or q.key in seen_keys:
            raise ValueError(f"Expected a new Python-identifier key on the {page} page, got {q.key!r}")
        if len(q.hotkey) != 1 or not q.hotkey.islower() or q.hotkey in seen_hotkeys:
            raise ValueError(f"Expected a free lower-case hotkey for {q.key} on the {page} page, got {q.hotkey!r}")
        if q.widget not in WIDGETS[page]:
            raise ValueError(f"Expected a widget in {', '.join(WIDGETS[page])} for {q.key}, got {q.widget!r}")
        if q.answer not in ANSWER_TYPES or q.aggregate not in AGGREGATIONS:
            raise ValueError(f"Expected answer {ANSWER_TYPES} aggregated by {AGGREGATIONS} for {q.key}")
        seen_keys.add(q.key)
        seen_hotkeys.add(q.hotkey)


check_table(JUDGE, "judge", JUDGE_RESERVED_KEYS)
check_table(GRID, "grid", GRID_RESERVED_KEYS)


def judge_questions() -> tuple[Question, ...]:
    """The judge task's questions, in page order (read when called, so a changed table is seen)."""
    return JUDGE


def grid_questions() -> tuple[Question, ...]:
    """The confirm grid's questions (taps), in button order."""
    return GRID


def keys(questions: Iterable[Question]) -> tuple[str, ...]:
    return tuple(q.key for q in questions)


def required_keys(questions: Iterable[Question]) -> tuple[str, ...]:
    """The keys every answer has (the rest are optional: older pages did not ask them)."""
    return tuple(q.key for q in questions if not q.optional)


def asked(questions: Iterable[Question], payloads: Iterable[Mapping[str, Any] | None]) -> tuple[Question, ...]:
    """The questions these answers were asked: the required ones, and an optional one when any
    answer has it (a batch answered on an older page has no ``swapped``)."""
    given = [p or {} for p in payloads]
    return tuple(q for q in questions if not q.optional or any(q.key in p for p in given))


def page_table(page: str) -> list[dict[str, Any]]:
    """The table as a page's script reads it (a ``<script type="application/json">`` block)."""
    questions = judge_questions() if page == "judge" else grid_questions()
    return [q.as_json() for q in questions]
