"""Fixtures of the crowd tests that run against the database."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select

from core.db import db
from core.models import Card, Collection


@pytest.fixture
def bare_cards(app):  # type: ignore[no-untyped-def]
    """``bare_cards(k)``: k card rows (no image files: the queue never opens them), their ids."""

    def make(k: int) -> list[int]:
        with app.app_context():
            group = db.session.scalar(select(Collection).where(Collection.name == "queue")) or Collection(name="queue")
            start = db.session.scalar(select(func.count()).select_from(Card))
            cards = [
                Card(
                    collection=group,
                    content_hash=f"{start + i:064x}",
                    stored_path=f"originals/{start + i}.png",
                    source_name=f"q{start + i}.png",
                    source_path=f"/q/{start + i}.png",
                    width=604,
                    height=200,
                    image_format="PNG",
                    byte_size=1,
                    source_metadata={},
                    state="review",
                )
                for i in range(k)
            ]
            db.session.add_all(cards)
            db.session.commit()
            return [c.id for c in cards]

    return make
