"""Accepted cards with real pipeline outputs, for the release tests.

Cards are the Motorcycle stereo card (real photographs); the filter result is written by the
shared factory and rectification and disparity are run by ``keystone run`` itself, so the
release reads the same artifacts the pipeline makes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest


@pytest.fixture
def review_card(app) -> Callable[..., None]:  # type: ignore[no-untyped-def]
    """Set (or change) a card's curator review: decision and final grade."""
    from sqlalchemy import select

    from core.db import db
    from review.models import CardReview

    def set_review(card_id: int, grade: str | None, decision: str = "accepted", auto_grade: str | None = None) -> None:
        with app.app_context():
            row = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
            if row is None:
                row = CardReview(card_id=card_id)
                db.session.add(row)
            row.grade, row.decision, row.auto_grade = grade, decision, auto_grade or grade
            db.session.commit()

    return set_review


@pytest.fixture
def processed_cards(app, runner, make_card, add_stage_result, decide_orientation) -> Callable[[int], list[int]]:  # type: ignore[no-untyped-def]
    """``n`` ingested cards with filter, rectify and disparity results (the real pipeline), their
    orientation decided by a curator (undecided cards are neither rectified nor released)."""

    def make(count: int) -> list[int]:
        ids = []
        for number in range(count):
            card_id = make_card(
                accession=f"1996.0009.{17827 + number}",
                metadata={
                    "title": f"Motorcycle {number}",
                    "date": "1890",
                    "url": f"https://emuseum.example.org/objects/{17827 + number}",
                },
                image=_variant(number),
            )
            add_stage_result(card_id, "filter")
            ids.append(card_id)
        decide_orientation(ids)
        result = runner.invoke(args=["run", "--stages", "rectify,disparity", "--json"])
        assert result.exit_code == 0, result.output
        return ids

    return make


def _variant(number: int) -> Any:
    """A distinct card per number (content hashes must differ): the same pair, another crop."""
    import numpy as np
    from PIL import Image
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    half = (296, 200)
    x0 = 12 * number
    views = [np.asarray(Image.fromarray(v[:, x0 : x0 + 700]).resize(half, Image.Resampling.BOX)) for v in (left, right)]
    strip = np.full((half[1], 12, 3), 200, np.uint8)
    return np.concatenate([views[0], strip, views[1]], axis=1)
