"""The 3D viewer's tests share one card with real views (tests/ is not a package: fixtures)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest


@pytest.fixture
def make_card_with_views(app, data_dir, make_card, add_stage_result) -> Callable[..., tuple[int, Any]]:  # type: ignore[no-untyped-def]
    """A stored card whose latest views result is the real output of ``views_task`` on the
    Motorcycle pair at ``width`` px with its ground-truth disparity; returns (card id, record)."""
    import cv2
    from skimage import data

    from pipeline.io import write_npy, write_png
    from pipeline.records import CardTask
    from pipeline.view_stage import ViewsStageParams, views_task

    def make(width: int = 160, grade: str = "few") -> tuple[int, Any]:
        left, _, disp = data.stereo_motorcycle()
        scale = width / left.shape[1]
        size = (width, round(left.shape[0] * scale))
        view = cv2.resize(np.asarray(left), size, interpolation=cv2.INTER_AREA)
        d = cv2.resize(np.asarray(disp, np.float32), size, interpolation=cv2.INTER_NEAREST) * scale
        write_png(data_dir / "rect" / "left.png", view)
        write_npy(data_dir / "rect" / "disparity_left.npy", np.where(np.isfinite(d), d, np.nan).astype(np.float32))
        card_id = make_card(state="pass")
        task = CardTask(card_id=card_id, content_hash="c" * 64, image_path="",
                        work_dir=str(data_dir / "derived" / "views"), data_dir=str(data_dir),
                        inputs={"left": "rect/left.png", "disparity_left": "rect/disparity_left.npy",
                                "focal_px": 3979.911 * scale, "grade": grade})
        record = views_task(task, ViewsStageParams(preview_side=120, preview_frames=4))
        assert record.status == "done", record.reason
        add_stage_result(card_id, "views", status="done", outcome=None, param_hash=record.param_hash,
                         metrics=record.metrics, artifacts=record.artifacts)
        return card_id, record

    return make
