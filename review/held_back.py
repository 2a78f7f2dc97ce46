"""Why a card in the review queue may not be accepted now, in the words of :mod:`runs.card_state`,
split the way a curator acts on it: the crowd disputes (each with its aggregate, so a page links
straight to the dispute) and the other blockers (an undecided orientation, a stale result).

The queue asks for a whole page at once (:func:`held_back_cards`): the page's cards with their
stage results in one query and :func:`runs.card_state.card_states` once for all of them, so
paging through the queue stays linear in the cards shown.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import selectinload

from core.db import db
from core.models import Card
from runs.card_state import CardState, card_states
from runs.specs import available_stages


@dataclass(frozen=True)
class Dispute:
    """A crowd answer on the card that waits for a curator."""

    aggregate_id: int
    reason: str  # "the crowd disagrees on its crop (batch 3, dispute 7)"


@dataclass(frozen=True)
class HeldBack:
    """What keeps one card from being accepted (or given another grade) now."""

    card_id: int
    reasons: tuple[str, ...]  # CardState.blockers: every reason in words, in its order
    disputes: tuple[Dispute, ...]

    @property
    def others(self) -> list[str]:
        """The reasons that are not crowd disputes (an undecided orientation, a stale result)."""
        disputed = {dispute.reason for dispute in self.disputes}
        return [reason for reason in self.reasons if reason not in disputed]


def held_back(state: CardState) -> HeldBack | None:
    """``state``'s blockers, its disputes apart; None when nothing holds the card back."""
    reasons = tuple(state.blockers)
    if not reasons:
        return None
    disputes = tuple(Dispute(wait.aggregate_id, wait.reason) for wait in state.disputes if wait.aggregate_id is not None)
    return HeldBack(state.card_id, reasons, disputes)


def held_back_cards(card_ids: Iterable[int]) -> dict[int, HeldBack]:
    """The held-back cards among ``card_ids`` (a page of the queue), by card id: one query for
    the cards and their stage results, one batch of :func:`runs.card_state.card_states`."""
    ids = sorted(set(card_ids))
    if not ids:
        return {}
    cards = list(db.session.scalars(select(Card).where(Card.id.in_(ids)).options(selectinload(Card.stage_results))))
    states = card_states(cards, specs=available_stages())
    return {card_id: found for card_id, state in states.items() if (found := held_back(state)) is not None}
