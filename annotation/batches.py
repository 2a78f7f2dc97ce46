"""Batches of crowd tasks: creating one, the card queues they are made from (review, orientation), the
card a preview shows."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from sqlalchemy import select

from app.db import db
from app.models import Card

from . import assignment as strategy
from .answers import validate_payload
from .models import TASK_KINDS, Aggregate, Batch, BatchItem
from .task_errors import TaskError


def create_batch(
    card_ids: Sequence[int],
    kind: str = "judge",
    n: int = 3,
    gold_rate: float = 0.1,
    *,
    gold: Mapping[int, dict[str, Any]] | None = None,
    created_by: int | None = None,
) -> Batch:
    """A batch over ``card_ids`` plus the gold cards in ``gold`` (card id -> known answer)."""
    if kind not in TASK_KINDS:
        raise TaskError(f"Expected kind judge or crop, got {kind!r}")
    if n < 1:
        raise TaskError(f"Expected at least 1 answer per item, got {n}")
    if not 0.0 <= gold_rate <= 1.0:
        raise TaskError(f"Expected 0 <= gold rate <= 1, got {gold_rate}")
    gold = dict(gold or {})
    wanted = list(dict.fromkeys([*card_ids, *gold]))
    if not wanted:
        raise TaskError("Expected at least one card, got none")
    found = set(db.session.scalars(select(Card.id).where(Card.id.in_(wanted))))
    missing = [c for c in wanted if c not in found]
    if missing:
        raise TaskError(f"No card with id {', '.join(map(str, missing))}", 404)
    cards = {c.id: c for c in db.session.scalars(select(Card).where(Card.id.in_(wanted)))}
    for card_id, answer in gold.items():
        validate_payload(kind, answer, cards[card_id])
    batch = Batch(kind=kind, answers_per_item=n, gold_rate=gold_rate, created_by=created_by)
    for card_id in wanted:
        batch.items.append(BatchItem(card_id=card_id, is_gold=card_id in gold, gold_answer=gold.get(card_id)))
    db.session.add(batch)
    db.session.flush()  # ids: the shuffle is keyed on them
    for item in batch.items:
        item.rank = strategy.item_rank(batch.id, item.id)
    db.session.commit()
    return batch


def review_queue_card_ids() -> list[int]:
    """Cards the filter sent to human judgement (state ``review``)."""
    return list(db.session.scalars(select(Card.id).where(Card.state == "review").order_by(Card.id)))


def orientation_queue_card_ids() -> list[int]:
    """Cards whose orientation the orientation step could not decide (it asked, or failed) and
    that no crowd judgement or curator has decided yet, whatever their filter band: they wait
    for a judge batch (``keystone crowd create-batch --from-review`` includes them)."""
    from app.runs import waiting_for_people

    waiting = waiting_for_people()["orientation"]
    # A card already in a judge batch whose answers are not aggregated yet is on its way.
    in_flight: set[int] = set()
    for start in range(0, len(waiting), 500):
        chunk = waiting[start : start + 500]
        in_flight.update(
            db.session.scalars(
                select(BatchItem.card_id)
                .join(Batch, Batch.id == BatchItem.batch_id)
                .where(
                    Batch.kind == "judge",
                    BatchItem.card_id.in_(chunk),
                    ~BatchItem.is_gold,
                    ~select(Aggregate.id)
                    .where(Aggregate.batch_id == BatchItem.batch_id, Aggregate.card_id == BatchItem.card_id)
                    .exists(),
                )
            )
        )
    return [card_id for card_id in waiting if card_id not in in_flight]


def preview_card() -> Card | None:
    """The card an MTurk preview shows: the first regular item of the oldest judge batch still open."""
    return db.session.scalar(
        select(Card)
        .join(BatchItem, BatchItem.card_id == Card.id)
        .join(Batch, Batch.id == BatchItem.batch_id)
        .where(Batch.kind == "judge", BatchItem.is_gold.is_(False), BatchItem.answers < Batch.answers_per_item)
        .order_by(Batch.id, BatchItem.id)
        .limit(1)
    )
