"""Batches of crowd tasks: creating one, the card queues they are made from (review, orientation), the
card a preview shows."""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from datetime import timedelta
from typing import Any

from sqlalchemy import select, text
from sqlalchemy.orm import selectinload

from core.audit import AuditEvent, record_event
from core.db import db, utcnow
from core.models import Card, Person, StageResult

from . import assignment as strategy, confirm as confirm_flags
from .answers import validate_payload
from .crowd_settings import grid_size
from .labels import batch_not_closed, batch_takes_new_tasks
from .models import TASK_KINDS, Aggregate, Batch, BatchItem
from .task_errors import TaskError

GOLD_AUTO_CONFIDENCE = 0.99  # the step's own decisions good enough to be gold
# How long a form's request key is remembered: a resubmit (a double click, a retried POST, the
# browser's back button and submit) within it gives the batch the first submit made.
REQUEST_KEY_DAYS = 7


class AlreadyCreated(Exception):
    """This request key already made a batch: nothing new was created."""

    def __init__(self, batch_id: int) -> None:
        super().__init__(f"batch {batch_id} was already created from this form")
        self.batch_id = batch_id


def _batch_made_for(request_key: str) -> int | None:
    """The batch a staff form with ``request_key`` made (its audit event), if any.

    Runs first in the creating transaction, so it is serialised with the creations: SQLite's write
    transactions begin IMMEDIATE (one at a time); on PostgreSQL an advisory lock on the key holds
    a second submit of the same form until the first one committed.
    """
    if db.session.get_bind().dialect.name == "postgresql":
        db.session.execute(text("SELECT pg_advisory_xact_lock(hashtext(:key))"), {"key": f"crowd-new-batch:{request_key}"})
    return db.session.scalar(
        select(AuditEvent.entity_id)
        .where(
            AuditEvent.entity == "crowd_batch",
            AuditEvent.action == "create",
            AuditEvent.at > utcnow() - timedelta(days=REQUEST_KEY_DAYS),
            AuditEvent.after["request_key"].as_string() == request_key,
        )
        .limit(1)
    )


def create_batch(
    card_ids: Sequence[int],
    kind: str = "judge",
    n: int = 3,
    gold_rate: float = 0.1,
    *,
    gold: Mapping[int, dict[str, Any]] | None = None,
    shown: Mapping[int, dict[str, bool]] | None = None,
    created_by: int | None = None,
    request_key: str | None = None,
) -> Batch:
    """A batch over ``card_ids`` plus the gold cards in ``gold`` (card id -> known answer).

    confirm batches: ``shown`` gives each card's orientation flags the grid shows it with
    (:func:`confirm_shown` for cards the step proposed; a gold card's deliberately wrong ones).
    ``request_key``: the staff form's one-time key; a second call with it raises
    :class:`AlreadyCreated` naming the first call's batch, and the creation is audited with it.
    """
    if request_key is not None:
        earlier = _batch_made_for(request_key)
        if earlier is not None:
            db.session.rollback()
            raise AlreadyCreated(earlier)
    if kind not in TASK_KINDS:
        raise TaskError(f"Expected kind {', '.join(TASK_KINDS)}, got {kind!r}")
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
    shown = _shown_flags(kind, wanted, shown, cards)
    batch = Batch(kind=kind, answers_per_item=n, gold_rate=gold_rate, created_by=created_by)
    for card_id in wanted:
        batch.items.append(
            BatchItem(card_id=card_id, is_gold=card_id in gold, gold_answer=gold.get(card_id), shown=shown.get(card_id))
        )
    db.session.add(batch)
    db.session.flush()  # ids: the shuffle is keyed on them
    for item in batch.items:
        item.rank = strategy.item_rank(batch.id, item.id)
    if request_key is not None:
        record_event(
            entity="crowd_batch",
            action="create",
            entity_id=batch.id,
            actor=db.session.get(Person, created_by) if created_by is not None else None,
            actor_label="web",
            after={"request_key": request_key, "kind": kind, "items": len(wanted), "answers_per_item": n},
            why=f"batch {batch.id} from the batches page",
        )
    db.session.commit()
    return batch


def _shown_flags(
    kind: str, card_ids: list[int], given: Mapping[int, dict[str, bool]] | None, cards: Mapping[int, Card]
) -> dict[int, dict[str, bool]]:
    """What each confirm card is shown with: ``given``, else the step's proposal; TaskError for
    a confirm card with neither (a grid cannot show a card nobody proposed a way up for)."""
    if kind != "confirm":
        if given:
            raise TaskError("Only confirm batches show cards with orientation flags")
        return {}
    shown: dict[int, dict[str, bool]] = {}
    for card_id in card_ids:
        flags = (given or {}).get(card_id) or confirm_shown(cards[card_id])
        if flags is None:
            raise TaskError(
                f"Card {card_id} has no proposed orientation to confirm (its orientation step did not say auto or confirm)"
            )
        try:
            shown[card_id] = confirm_flags.as_flags(flags)
        except KeyError as exc:
            raise TaskError(f"Expected the flags shown for card {card_id} to give {exc.args[0]}") from None
    return shown


def confirm_shown(card: Card) -> dict[str, bool] | None:
    """The orientation the grid shows a card with: the step's ``proposed`` flags (card as scanned)."""
    step = card.latest_results().get("orientation")
    proposed = step.metrics.get("proposed") if step is not None and step.status == "done" else None
    if not isinstance(proposed, dict) or any(not isinstance(proposed.get(f), bool) for f in confirm_flags.FLAGS):
        return None
    return confirm_flags.as_flags(proposed)


def review_queue_card_ids() -> list[int]:
    """Cards the filter sent to human judgement (state ``review``)."""
    return list(db.session.scalars(select(Card.id).where(Card.state == "review").order_by(Card.id)))


def cards_in_open_batches(kind: str, card_ids: Sequence[int], *, answered_too: bool = True) -> set[int]:
    """Of ``card_ids``, those with a regular item in a ``kind`` batch that is not closed: work
    already asked for (a paused batch's cards wait for it). ``answered_too=False`` leaves out
    items the crowd's answer was reached for (an aggregate), as the orientation queues do: a card
    a grid could not agree on goes to a judge batch again."""
    busy: set[int] = set()
    ids = list(card_ids)
    for start in range(0, len(ids), 500):
        query = (
            select(BatchItem.card_id)
            .join(Batch, Batch.id == BatchItem.batch_id)
            .where(Batch.kind == kind, BatchItem.card_id.in_(ids[start : start + 500]), ~BatchItem.is_gold, batch_not_closed())
        )
        if not answered_too:
            query = query.where(
                ~select(Aggregate.id)
                .where(Aggregate.batch_id == BatchItem.batch_id, Aggregate.card_id == BatchItem.card_id)
                .exists()
            )
        busy.update(db.session.scalars(query))
    return busy


def waiting_card_ids(kind: str) -> list[int]:
    """The cards a new ``kind`` batch made "from the queue" on the batches page takes, none that
    is already in a batch of that kind that is not closed: judge, the filter's review band and the
    cards whose orientation waits for people; crop, the review band; confirm, the cards waiting
    for a grid (``keystone crowd create-batch --from-review`` takes the queues as they are)."""
    if kind == "confirm":
        return confirm_queue_card_ids()
    band = review_queue_card_ids()
    busy = cards_in_open_batches(kind, band)
    ids = [card_id for card_id in band if card_id not in busy]
    if kind == "judge":
        ids = list(dict.fromkeys(ids + orientation_queue_card_ids()))
    return ids


def _step_outcomes(card_ids: list[int]) -> dict[int, str | None]:
    """The outcome of each card's latest orientation result (the latest row, as Card.latest_results)."""
    outcomes: dict[int, str | None] = {}
    for start in range(0, len(card_ids), 500):
        rows = db.session.execute(
            select(StageResult.card_id, StageResult.outcome)
            .where(StageResult.stage == "orientation", StageResult.card_id.in_(card_ids[start : start + 500]))
            .order_by(StageResult.id)
        )
        outcomes.update({card_id: outcome for card_id, outcome in rows})
    return outcomes


def _escalated(card_ids: list[int]) -> set[int]:
    """Cards whose latest confirm aggregate says the grid could not agree (state ``escalated``)."""
    latest: dict[int, str] = {}
    for start in range(0, len(card_ids), 500):
        rows = db.session.execute(
            select(Aggregate.card_id, Aggregate.state)
            .where(Aggregate.kind == "confirm", Aggregate.card_id.in_(card_ids[start : start + 500]))
            .order_by(Aggregate.id)
        )
        latest.update({card_id: state for card_id, state in rows})
    return {card_id for card_id, state in latest.items() if state == "escalated"}


def orientation_queue_card_ids() -> list[int]:
    """Cards whose orientation the orientation step could not decide (it asked, or failed) and
    that no crowd judgement or curator has decided yet, whatever their filter band: they wait
    for a judge batch (``keystone crowd create-batch --from-review`` includes them). Cards the
    step proposed an orientation for (``confirm``) wait for a grid instead
    (:func:`confirm_queue_card_ids`), unless a grid could not agree on them."""
    return _waiting_for_orientation("judge")


def confirm_queue_card_ids() -> list[int]:
    """Cards whose orientation step proposed an orientation with a narrow margin (``confirm``)
    and that nobody has decided yet: they wait for a confirm batch (a grid)."""
    return _waiting_for_orientation("confirm")


def _waiting_for_orientation(kind: str) -> list[int]:
    from runs.card_state import waiting_for_people

    waiting = waiting_for_people()["orientation"]
    outcomes, escalated = _step_outcomes(waiting), _escalated(waiting)
    # A grid that could not agree on a card sends it to a judge task: people judge it from scratch.
    waiting = [
        card_id for card_id in waiting if (outcomes.get(card_id) == "confirm" and card_id not in escalated) == (kind == "confirm")
    ]
    # A card already in a batch of this kind (not closed) whose answers are not aggregated yet is on its way.
    in_flight: set[int] = set()
    for start in range(0, len(waiting), 500):
        chunk = waiting[start : start + 500]
        in_flight.update(
            db.session.scalars(
                select(BatchItem.card_id)
                .join(Batch, Batch.id == BatchItem.batch_id)
                .where(
                    Batch.kind == kind,
                    BatchItem.card_id.in_(chunk),
                    ~BatchItem.is_gold,
                    batch_not_closed(),
                    ~select(Aggregate.id)
                    .where(Aggregate.batch_id == BatchItem.batch_id, Aggregate.card_id == BatchItem.card_id)
                    .exists(),
                )
            )
        )
    return [card_id for card_id in waiting if card_id not in in_flight]


def confirm_gold_needed(cards: int) -> int:
    """Gold items a confirm batch of ``cards`` needs so a worker who answers every card of it
    meets fresh gold in every grid (each worker sees a gold item once), and at least four (one
    shown right, one wrong on each flag)."""
    size, gold = grid_size()
    return max(4, math.ceil(cards / max(1, size - gold)) * gold)


def confirm_gold(exclude: Collection[int], count: int | None = None) -> tuple[dict[int, dict], dict[int, dict]]:
    """Gold for a confirm batch: up to ``count`` (default :func:`confirm_gold_needed` for the
    cards of ``exclude``) cards whose orientation is known (a curator's,
    the crowd's, or the step's own with a wide margin: confidence >= :data:`GOLD_AUTO_CONFIDENCE`),
    none of ``exclude``; each shown wrong on one flag in turn, or right
    (:func:`annotation.confirm.gold_shown`). Returns ``(gold taps, shown flags)`` by card id.

    Curators' and the crowd's decisions come first: the step's own are right only as often as
    its confidence says."""
    from core.hooks import approved_decisions
    from pipeline.decided_orientation import card_orientation

    count = confirm_gold_needed(len(exclude)) if count is None else count
    excluded, known = set(exclude), []
    after = 0
    while len(known) < 4 * count:
        cards = list(
            db.session.scalars(
                select(Card)
                .where(Card.state == "pass", Card.id > after)
                .order_by(Card.id)
                .limit(500)
                .options(selectinload(Card.stage_results))
            )
        )
        if not cards:
            break
        approved = approved_decisions([card.id for card in cards])
        for card in cards:
            if card.id in excluded or "orientation" not in card.latest_results():
                continue
            used = card_orientation(card, approved.get(card.id, {}))
            sure = used["decided_by"] in ("curator", "crowd") or (
                used["decided_by"] == "auto" and (used["confidence"] or 0.0) >= GOLD_AUTO_CONFIDENCE
            )
            if sure and confirm_shown_boxes_ok(card):
                known.append((used["decided_by"] == "auto", card.id, confirm_flags.as_flags(used)))
        after = cards[-1].id
    taps: dict[int, dict] = {}
    shown: dict[int, dict] = {}
    for turn, (_, card_id, truth) in enumerate(sorted(known)[:count]):
        shown[card_id] = confirm_flags.gold_shown(truth, turn)
        taps[card_id] = confirm_flags.taps_between(shown[card_id], truth)
    return taps, shown


def confirm_shown_boxes_ok(card: Card) -> bool:
    """Whether a grid can cut the card's two photos: a done filter or orientation result with boxes."""
    latest = card.latest_results()
    return any(
        result is not None and result.status == "done" and result.metrics.get(left) and result.metrics.get(right)
        for result, left, right in (
            (latest.get("orientation"), "photo_left_box", "photo_right_box"),
            (latest.get("filter"), "left_box", "right_box"),
        )
    )


def preview_card() -> Card | None:
    """The card an MTurk preview shows: the first regular item of the oldest judge batch still open."""
    return db.session.scalar(
        select(Card)
        .join(BatchItem, BatchItem.card_id == Card.id)
        .join(Batch, Batch.id == BatchItem.batch_id)
        .where(
            Batch.kind == "judge",
            BatchItem.is_gold.is_(False),
            BatchItem.answers < Batch.answers_per_item,
            batch_takes_new_tasks(),
        )
        .order_by(Batch.id, BatchItem.id)
        .limit(1)
    )
