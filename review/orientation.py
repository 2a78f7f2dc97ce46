"""Curators and a card's orientation: the override (any flag), and what holds a card back.

A curator can set any of ``upside_down``, ``inverted`` and ``swapped`` on a card (or clear a
flag, giving it back to the orientation step and the crowd); the override and an audit event
(entity ``orientation``, before and after the orientation the pipeline uses) are committed
together. The card's rectification inputs change with it, so the next ``keystone run`` redoes
rectification, disparity and grade with the new orientation.

:func:`flow_blockers` says, in sentences, why a card may not be accepted or released now: its
orientation is undecided, the crowd's judgement or crop waits for a curator, or the grade was
computed from an orientation that has changed since.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from sqlalchemy import select

from core.audit import record_event
from core.db import db
from core.models import Card, Person
from pipeline.decided_orientation import FLAGS, is_decided, public_orientation

from .models import OrientationOverride
from .tasks import MAX_NOTE_CHARS, ReviewError

__all__ = ["current_orientation", "flow_blockers", "flow_blockers_for", "override_orientation"]


def current_orientation(card: Card) -> dict[str, Any]:
    """The orientation the pipeline uses for ``card`` (see :mod:`pipeline.decided_orientation`)."""
    from pipeline.decided_orientation import card_orientation
    from runs.specs import approved_annotations

    return card_orientation(card, approved_annotations([card.id]).get(card.id, {}))


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


def flow_blockers(card: Card) -> list[str]:
    """Why ``card`` may not be accepted or released now (empty: nothing holds it back)."""
    return flow_blockers_for([card])[card.id]


def flow_blockers_for(cards: list[Card]) -> dict[int, list[str]]:
    """:func:`flow_blockers` for many cards with three queries (cards' results loaded)."""
    from annotation.models import Aggregate
    from pipeline.decided_orientation import card_orientation
    from runs.specs import approved_annotations

    ids = [card.id for card in cards]
    approved = approved_annotations(ids)
    latest: dict[int, dict[str, Aggregate]] = {}
    for start in range(0, len(ids), 500):
        for row in db.session.scalars(
            select(Aggregate).where(Aggregate.card_id.in_(ids[start : start + 500])).order_by(Aggregate.id)
        ):
            latest.setdefault(row.card_id, {})[row.kind] = row
    blockers: dict[int, list[str]] = {}
    for card in cards:
        found = blockers[card.id] = []
        orientation = card_orientation(card, approved.get(card.id, {}))
        if not is_decided(orientation):
            found.append(f"its orientation is undecided (waiting for {orientation['waiting_for']})")
        for kind, row in sorted(latest.get(card.id, {}).items()):
            if row.state == "needs_curator":
                what = "judgement" if kind == "judge" else "crop"
                found.append(f"the crowd disagrees on its {what} (batch {row.batch_id}, dispute {row.id})")
        rectify = card.latest_results().get("rectify")
        if rectify is not None and is_decided(orientation):
            used = rectify.metrics.get("orientation_used")
            if used is not None and any(used.get(flag) != orientation[flag] for flag in FLAGS):
                found.append(
                    "it was rectified and graded with another orientation "
                    f"({', '.join(f'{f}={used.get(f)}' for f in FLAGS)}); run the pipeline again"
                )
    return blockers
