"""What a pipeline run needs from curator review, registered with the app (see :mod:`core.hooks`)."""

from __future__ import annotations

from typing import Any

from flask import Flask
from sqlalchemy import select
from sqlalchemy.orm import joinedload, selectinload

from core.db import db
from core.hooks import stage_hooks
from core.models import Card, CollectionOrientation

from .models import CardReview, OrientationOverride

CHUNK = 500  # card ids per query: under SQLite's bound-parameter limit


def card_reviews(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """The curator review per card: ``{card: {"review": CardReview}}``."""
    found: dict[int, dict[str, Any]] = {}
    for start in range(0, len(card_ids), CHUNK):
        rows = db.session.scalars(select(CardReview).where(CardReview.card_id.in_(card_ids[start : start + CHUNK])))
        for review in rows:
            found.setdefault(review.card_id, {})["review"] = review
    return found


def orientation_overrides(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """A curator's orientation override per card: ``{card: {"orientation_override": row}}``
    (pipeline.decided_orientation resolves the orientation the pipeline uses from it)."""
    found: dict[int, dict[str, Any]] = {}
    for start in range(0, len(card_ids), CHUNK):
        rows = db.session.scalars(
            select(OrientationOverride)
            .where(OrientationOverride.card_id.in_(card_ids[start : start + CHUNK]))
            .options(selectinload(OrientationOverride.curator))
        )
        for row in rows:
            found.setdefault(row.card_id, {})["orientation_override"] = row
    return found


def operator_words(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """The operator's word for each card's collection, where there is one:
    ``{card: {"operator_orientation": row}}`` (one query per chunk of cards; the cards of a
    collection share its row)."""
    found: dict[int, dict[str, Any]] = {}
    for start in range(0, len(card_ids), CHUNK):
        rows = db.session.execute(
            select(Card.id, CollectionOrientation)
            .join(CollectionOrientation, CollectionOrientation.collection_id == Card.collection_id)
            .where(Card.id.in_(card_ids[start : start + CHUNK]))
            .options(joinedload(CollectionOrientation.collection))
        )
        for card_id, word in rows:
            found.setdefault(card_id, {})["operator_orientation"] = word
    return found


def _grade_params() -> Any:
    from .grading import active_grade_params

    params, _ = active_grade_params()
    return params


def _upright_heads(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    # the learned head a collection refitted (keystone orientation fit), for the orientation step
    from .upright_fit import upright_head_inputs

    return upright_head_inputs(card_ids)


def _sync_new_grades(card_ids: list[int]) -> None:
    # New automatic grades reach the curators' queue at once (decided cards keep theirs).
    from .tasks import sync_reviews

    sync_reviews(card_ids)


def register(app: Flask) -> None:
    hooks = stage_hooks(app)
    hooks.people_work.append(card_reviews)
    hooks.decisions.append(orientation_overrides)
    hooks.decisions.append(operator_words)
    hooks.decisions.append(_upright_heads)
    hooks.stage_params["grade"] = _grade_params
    hooks.after_write.setdefault("grade", []).append(_sync_new_grades)
