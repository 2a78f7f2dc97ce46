"""Planning: which cards a stage still owes, with their inputs and the result each may replace."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any

from sqlalchemy import exists, func, select
from sqlalchemy.orm import selectinload

from core.db import db
from core.hooks import approved_decisions
from core.models import Card, StageResult
from runs.claims import result_fingerprint
from runs.specs import StageSpec


def inputs_digest(inputs: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:16]


PLAN_CHUNK = 500  # cards read and planned per step (and ids per IN list, under SQLite's bound-parameter
# limit): memory stays flat at any catalogue size


@dataclass(frozen=True)
class PlannedCard:
    """A card a stage still has to compute, with what the run needs to send it out: its inputs
    and the fingerprint of the result row it may replace (``None`` when there is none)."""

    card_id: int
    content_hash: str
    stored_path: str
    inputs: dict[str, Any]
    fingerprint: Any


def pending_cards(spec: StageSpec, phash: str, chunk: int = PLAN_CHUNK) -> tuple[list[PlannedCard], int]:
    """Cards that still need ``spec`` with these parameters (with their inputs), and how many
    are already finished. A finished card runs again when its inputs changed (say the crowd's
    boxes arrived after the automatic split was used).

    A stage without inputs is planned in SQL (cards with no finished result for this parameter
    hash); a stage with inputs reads the eligible card ids in one query, then the cards in chunks of ``chunk`` by id,
    computes each card's inputs and lets the chunk's rows go, so planning never holds the whole
    catalogue in memory.
    """
    eligible = Card.state.in_(spec.eligible_states)
    if spec.requires is not None:
        eligible = eligible & exists().where(
            StageResult.card_id == Card.id,
            StageResult.stage == spec.requires,
            StageResult.status.in_(("done", "skipped")),
        )
    already = 0
    if spec.inputs is None:
        finished = exists().where(
            StageResult.card_id == Card.id,
            StageResult.stage == spec.name,
            StageResult.param_hash == phash,
            StageResult.status.in_(("done", "skipped")),
        )
        already = db.session.scalar(select(func.count()).select_from(Card).where(eligible, finished)) or 0
        eligible = eligible & ~finished
        if spec.ready is None:
            # Nothing to compute per card: the plan is one query over plain columns, with the
            # row a result would replace (a failed one) joined in.
            own = StageResult.__table__.alias("own")
            rows = db.session.execute(
                select(Card.id, Card.content_hash, Card.stored_path, own.c.status, own.c.started_at)
                .outerjoin(own, (own.c.card_id == Card.id) & (own.c.stage == spec.name) & (own.c.param_hash == phash))
                .where(eligible)
                .order_by(Card.id)
            )
            return [
                PlannedCard(
                    card_id, content_hash, stored_path, {}, None if status is None else result_fingerprint(status, started_at)
                )
                for card_id, content_hash, stored_path, status, started_at in rows
            ], already
    todo: list[PlannedCard] = []
    # The eligible ids in one query (a few MB at 250,000 cards), then the cards chunk by chunk
    # by id. Paging the eligible query itself (``id > after LIMIT chunk``) let PostgreSQL
    # re-evaluate the ``requires`` semi-join over every stage result for every chunk, which
    # grew with the square of the catalogue.
    eligible_ids = list(db.session.scalars(select(Card.id).where(eligible).order_by(Card.id)))
    for start in range(0, len(eligible_ids), chunk):
        cards = list(
            db.session.scalars(
                select(Card)
                .where(Card.id.in_(eligible_ids[start : start + chunk]))
                .order_by(Card.id)
                .options(selectinload(Card.stage_results))
            )
        )
        approved = approved_decisions([card.id for card in cards]) if spec.inputs is not None else {}
        for card in cards:
            inputs = spec.inputs(card, approved.get(card.id, {})) if spec.inputs is not None else {}
            if spec.ready is not None and not spec.ready(card, inputs):
                continue
            own = next((r for r in card.stage_results if r.stage == spec.name and r.param_hash == phash), None)
            if (
                own is not None
                and own.status in ("done", "skipped")
                and (spec.inputs is None or own.metrics.get("inputs_digest") == inputs_digest(inputs))
            ):
                already += 1
                continue
            todo.append(
                PlannedCard(
                    card.id,
                    card.content_hash,
                    card.stored_path,
                    inputs,
                    None if own is None else result_fingerprint(own.status, own.started_at),
                )
            )
        db.session.expunge_all()  # this chunk is planned: let its cards and results go
    return todo, already
