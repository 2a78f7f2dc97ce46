"""What a pipeline run needs from the crowd, registered with the app (see :mod:`core.hooks`)."""

from __future__ import annotations

from typing import Any

from flask import Flask
from sqlalchemy import func, select

from core.db import db
from core.hooks import stage_hooks

from .models import Aggregate

CHUNK = 500  # card ids per query: under SQLite's bound-parameter limit


def _aggregates(card_ids: list[int], approved_only: bool) -> dict[int, dict[str, Any]]:
    """The latest aggregate per card and task kind: ``{card: {"judge": Aggregate, "crop": Aggregate, "confirm": Aggregate}}``."""
    found: dict[int, dict[str, Any]] = {}
    for start in range(0, len(card_ids), CHUNK):
        query = select(Aggregate).where(Aggregate.card_id.in_(card_ids[start : start + CHUNK]))
        if approved_only:
            query = query.where(Aggregate.state == "approved")
        for row in db.session.scalars(query.order_by(Aggregate.id)):
            found.setdefault(row.card_id, {})[row.kind] = row
    return found


def approved_aggregates(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """Approved crowd judgements and crops: they feed rectification's inputs."""
    return _aggregates(card_ids, approved_only=True)


def latest_aggregates(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """The crowd's latest aggregate per kind in any state: the judge and crop stages' status."""
    return _aggregates(card_ids, approved_only=False)


def aggregates_mark() -> tuple[Any, ...]:
    """What moves when the crowd's aggregates do (a new one, or one approved or resolved): the
    background worker's cue that crowd work arrived (runs.worker.change_mark). Two index
    lookups (the id, the indexed ``updated_at``), so a worker can ask every few seconds at any
    catalogue size; a count would scan the table (126 ms at 500,000 aggregates on SQLite)."""
    # Two scalar subqueries: SQLite answers a lone max() from the index, but not two in one SELECT
    # (112 ms at 500,000 aggregates that way, 0.03 ms this way).
    newest = select(func.max(Aggregate.id)).scalar_subquery()
    changed = select(func.max(Aggregate.updated_at)).scalar_subquery()
    found = db.session.execute(select(newest, changed)).one()
    return (found[0], str(found[1]))


def register(app: Flask) -> None:
    hooks = stage_hooks(app)
    hooks.decisions.append(approved_aggregates)
    hooks.people_work.append(latest_aggregates)
    hooks.change_marks.append(aggregates_mark)
