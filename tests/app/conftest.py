"""Fixtures of the app's tests (tests/ is not a package): two photos mounted as a card, a card
with real views for the 3D viewer's tests, and a world with something behind every door for the
hostile-input tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest


def _mounted(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    gap = np.full((left.shape[0], 24, 3), (214, 200, 170), np.uint8)
    return np.concatenate([left, gap, right], axis=1)


@pytest.fixture(scope="session")
def mount_pair() -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``mount_pair(left, right)``: two RGB photos of one height side by side on a buff card
    with a 24 px gutter, as the test cards of ``keystone run`` are made."""
    return _mounted


@pytest.fixture
def make_card_with_views(app, data_dir, make_card, add_stage_result) -> Callable[..., tuple[int, Any]]:  # type: ignore[no-untyped-def]
    """A stored card whose latest views result is the real output of ``views_task`` on the
    Motorcycle pair at ``width`` px with its ground-truth disparity; returns (card id, record)."""
    import cv2
    from skimage import data

    from pipeline.io import write_npy, write_png
    from pipeline.records import CardTask
    from pipeline.stages.views import views_task
    from pipeline.view_synthesis import ViewsStageParams

    def make(width: int = 160, grade: str = "few") -> tuple[int, Any]:
        left, _, disp = data.stereo_motorcycle()
        scale = width / left.shape[1]
        size = (width, round(left.shape[0] * scale))
        view = cv2.resize(np.asarray(left), size, interpolation=cv2.INTER_AREA)
        d = cv2.resize(np.asarray(disp, np.float32), size, interpolation=cv2.INTER_NEAREST) * scale
        write_png(data_dir / "rect" / "left.png", view)
        write_npy(data_dir / "rect" / "disparity_left.npy", np.where(np.isfinite(d), d, np.nan).astype(np.float32))
        card_id = make_card(state="pass")
        task = CardTask(
            card_id=card_id,
            content_hash="c" * 64,
            image_path="",
            work_dir=str(data_dir / "derived" / "views"),
            data_dir=str(data_dir),
            inputs={
                "left": "rect/left.png",
                "disparity_left": "rect/disparity_left.npy",
                "focal_px": 3979.911 * scale,
                "grade": grade,
            },
        )
        record = views_task(task, ViewsStageParams(preview_side=120, preview_frames=4))
        assert record.status == "done", record.reason
        add_stage_result(
            card_id,
            "views",
            status="done",
            outcome=None,
            param_hash=record.param_hash,
            metrics=record.metrics,
            artifacts=record.artifacts,
        )
        return card_id, record

    return make


@dataclass(frozen=True)
class World:
    """A small served app with something behind every door (see :func:`hostile_world`)."""

    card_id: int  # filter-passed, graded and in the review queue
    review_id: int
    review_version: int
    crop_card_id: int  # in a crop batch wanting 1,000 answers per item
    aggregate_id: int  # a disputed crowd aggregate on crop_card_id
    worker_token: str  # a crowd worker's signed API token
    csrf: str  # the logged-in admin's CSRF token


@pytest.fixture
def hostile_world(app, client, login, csrf_token, make_card, add_stage_result, card_image, decide_orientation) -> World:  # type: ignore[no-untyped-def]
    """An admin logged in on ``client``, a reviewable card, a crop batch, a worker and a dispute."""
    import re

    from sqlalchemy import select

    from annotation.batches import create_batch
    from annotation.models import Aggregate
    from annotation.providers import InviteProvider
    from core.db import db
    from review.models import CardReview
    from review.tasks import sync_reviews

    image = card_image()
    card_id = make_card(image, state="pass")
    add_stage_result(card_id, "filter")
    add_stage_result(card_id, "grade", outcome="some", metrics={"uncertainty": 0.4, "reasons": ["fringes"]})
    decide_orientation([card_id])  # the flow rule: only a card with a decided orientation can be accepted
    crop_card_id = make_card(image[:, 8:], state="review")  # 596 x 200 px
    with app.app_context():
        sync_reviews()
        review_id, version = db.session.execute(
            select(CardReview.id, CardReview.version).where(CardReview.card_id == card_id)
        ).one()
        batch = create_batch([crop_card_id], "crop", 1000, 0.0)  # room for many workers' answers
        aggregate = Aggregate(
            batch_id=batch.id,
            card_id=crop_card_id,
            kind="crop",
            state="needs_curator",
            answers=2,
            label={"left": [0, 0, 280, 200], "right": [300, 0, 590, 200]},
            reasons="disputed",
        )
        db.session.add(aggregate)
        db.session.commit()
        aggregate_id = aggregate.id
        link = InviteProvider.invite("probe-worker").token
    page = client.get(f"/crowd/invite/{link}?kind=crop").get_data(as_text=True)
    worker_token = re.search(r'data-worker-token="([^"]*)"', page).group(1)  # type: ignore[union-attr]
    login("admin")
    return World(card_id, review_id, version, crop_card_id, aggregate_id, worker_token, csrf_token("/cards"))
