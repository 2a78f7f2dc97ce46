"""Writing results: one upsert per batch, card states, claims released, decisions changed."""

from __future__ import annotations

from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.dialects import postgresql, sqlite

from core.db import db, one_writer, utcnow
from core.models import Card, StageResult
from pipeline.records import StageRecord
from runs.claims import Driver


def decision_words(decision: Mapping[str, Any]) -> str:
    proposed = decision.get("proposed") or {}
    set_flags = [flag for flag, value in proposed.items() if value]
    return f"{decision.get('decision')} ({', '.join(set_flags) or 'upright, positive, eyes in order'})"


def _decision(outcome: str | None, metrics: Mapping[str, Any]) -> dict[str, Any]:
    return {"decision": outcome, "proposed": metrics.get("proposed")}


def decided_changes(session: Any, records: list[StageRecord]) -> list[dict[str, Any]]:
    """Of new orientation records, those whose decision (``auto`` / ``confirm`` / ``ask`` and the
    proposed flags) differs from the card's latest orientation result before them: what a
    collection's refitted head or an operator's word changed, listed in the run's report."""
    new = {r.card_id: r for r in records if r.stage == "orientation" and r.status == "done"}
    if not new:
        return []
    before: dict[int, dict[str, Any]] = {}
    for row in session.scalars(
        select(StageResult)
        .where(StageResult.stage == "orientation", StageResult.status == "done", StageResult.card_id.in_(new))
        .order_by(StageResult.id)
    ):
        before[row.card_id] = _decision(row.outcome, row.metrics or {})
    return [
        {"card_id": card_id, "before": before[card_id], "after": after}
        for card_id, record in sorted(new.items())
        if card_id in before and (after := _decision(record.outcome, record.metrics)) != before[card_id]
    ]


def write_records(
    records: list[StageRecord], digests: dict[int, str] | None = None, driver: Driver | None = None
) -> list[dict[str, Any]]:
    """Upsert results (one row per card, stage and parameters), update card states and release
    the driver's claims on these cards, in one transaction. Returns the orientation decisions the
    records changed (:func:`decided_changes`).

    An upsert, not read-then-insert: a row another run wrote meanwhile (its claim lapsed and
    was taken over, or it ran before claims existed) is overwritten, never a unique-key error.
    """
    if not records:
        return []
    session = db.session()
    with one_writer(session):
        changes = decided_changes(session, records)
        connection = session.connection()
        insert = (postgresql.insert if connection.dialect.name == "postgresql" else sqlite.insert)(StageResult)
        now = utcnow()
        rows = [
            {
                "card_id": record.card_id,
                "stage": record.stage,
                "param_hash": record.param_hash,
                "status": record.status,
                "outcome": record.outcome,
                "reason": record.reason,
                "metrics": {**record.metrics, "inputs_digest": digests[record.card_id]} if digests else record.metrics,
                "artifacts": record.artifacts,
                "started_at": datetime.fromtimestamp(record.started_at, tz=UTC) if record.started_at else None,
                "seconds": record.seconds,
                "code_version": record.code_version,
                "created_at": now,
            }
            # One row per key and statement (PostgreSQL refuses to upsert a row twice in one
            # command); the latest record of a card wins, as it would row by row. Key order is
            # the lock order, so two writers of the same rows queue instead of deadlocking.
            for _, record in sorted({(r.card_id, r.stage, r.param_hash): r for r in records}.items())
        ]
        updated = {
            column: getattr(insert.excluded, column)
            for column in ("status", "outcome", "reason", "metrics", "artifacts", "started_at", "seconds", "code_version")
        }
        connection.execute(
            insert.values(rows).on_conflict_do_update(index_elements=["card_id", "stage", "param_hash"], set_=updated)
        )
        cards = {card.id: card for card in session.scalars(select(Card).where(Card.id.in_({r.card_id for r in records})))}
        for record in records:
            card = cards.get(record.card_id)
            if card is not None and record.stage == "filter":
                card.state = record.outcome if record.status == "done" and record.outcome else "failed"
        if driver is not None:
            for stage in {record.stage for record in records}:
                connection.execute(driver.release_statement(stage, {r.card_id for r in records if r.stage == stage}))
        session.commit()
    return changes
