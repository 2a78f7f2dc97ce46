"""Curators and a card's orientation: the override (any flag), and what holds a card back.

A curator can set any of ``upside_down``, ``inverted`` and ``swapped`` on a card (or clear a
flag, giving it back to the orientation step and the crowd); the override and an audit event
(entity ``orientation``, before and after the orientation the pipeline uses) are committed
together. The card's rectification inputs change with it, so the next ``keystone run`` redoes
rectification, disparity and grade with the new orientation.

Why a card may not be accepted or released now (an undecided orientation among it) is
:attr:`runs.card_state.CardState.blockers`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from sqlalchemy import select

from core.audit import record_event
from core.db import db
from core.models import Card, Person
from pipeline.decided_orientation import FLAGS, public_orientation

from .models import OrientationOverride
from .tasks import MAX_NOTE_CHARS, ReviewError

__all__ = ["current_orientation", "override_orientation"]


def current_orientation(card: Card) -> dict[str, Any]:
    """The orientation the pipeline uses for ``card`` (see :mod:`pipeline.decided_orientation`)."""
    from core.hooks import approved_decisions
    from pipeline.decided_orientation import card_orientation

    return card_orientation(card, approved_decisions([card.id]).get(card.id, {}))


def _flag_value(name: str, value: Any) -> bool | None:
    if value is None or isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("", "none", "null", "keep", "auto"):
        return None
    if text in ("true", "yes", "1", "on"):
        return True
    if text in ("false", "no", "0", "off"):
        return False
    raise ReviewError(f"Expected {name} to be yes, no or empty (leave it to the step and the crowd), got {value!r}")


def override_orientation(card_id: int, flags: Mapping[str, Any], *, curator: Person, note: str = "") -> dict[str, Any]:
    """Set (true/false) or clear (None) the curator's word on each flag of ``card_id``; returns
    the orientation the pipeline now uses. Flags not named in ``flags`` keep their override."""
    unknown = sorted(set(flags) - set(FLAGS))
    if unknown:
        raise ReviewError(f"Unknown orientation flag(s) {', '.join(unknown)}; expected {', '.join(FLAGS)}")
    values = {name: _flag_value(name, value) for name, value in flags.items()}
    note = (note or "").strip()
    if len(note) > MAX_NOTE_CHARS:
        raise ReviewError(f"Expected a note of at most {MAX_NOTE_CHARS} characters, got {len(note)}")
    card = db.session.get(Card, card_id)
    if card is None:
        raise ReviewError(f"There is no card {card_id}", 404)
    if card.state not in ("pass", "review"):
        raise ReviewError(
            f"Card {card_id} is {card.state}: only cards the filter passed or sent to review have an orientation to decide"
        )
    before = public_orientation(current_orientation(card))
    row = db.session.scalar(select(OrientationOverride).where(OrientationOverride.card_id == card_id))
    if row is None:
        row = OrientationOverride(card_id=card_id, note="")
        db.session.add(row)
    for name, value in values.items():
        setattr(row, name, value)
    row.curator_id, row.curator, row.note = curator.id, curator, note
    db.session.flush()
    after = public_orientation(current_orientation(card))
    record_event(
        entity="orientation",
        action="override",
        card_id=card_id,
        entity_id=row.id,
        actor=curator,
        before=before,
        after={**after, "override": {name: getattr(row, name) for name in FLAGS}},
        why=note,
    )
    db.session.commit()
    return after
