"""The filter stage task: split the card at its gutter and route it by SIFT good-match fraction."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..filter import FilterParams, filter_card
from ..io import read_image, write_jpeg, write_npy
from ..records import CardTask
from ..split import crop_halves
from .base import PREVIEW_MAX_SIDE, StageOutput, stage_task

__all__ = ["filter_task"]


@stage_task("filter")
def filter_task(task: CardTask, params: FilterParams) -> StageOutput:
    """Split the card at its gutter and route it by SIFT good-match fraction."""
    card = read_image(task.image_path)
    split, result = filter_card(card, params)
    left, right = crop_halves(card, split)
    work_dir = Path(task.work_dir)
    artifacts = {}
    for name, half in (("left", left), ("right", right)):
        target = work_dir / f"{name}.jpg"
        write_jpeg(target, half, max_side=PREVIEW_MAX_SIDE)
        artifacts[name] = str(target.relative_to(task.data_dir))
    # The good matches in card px, (N, 4) [x_left, y_left, x_right, y_right]: the rectify stage
    # aligns the crops and rectifies from them instead of running SIFT on the photos again.
    (lx, ly), (rx, ry) = split.left_box[:2], split.right_box[:2]
    matches = np.hstack([result.points[0] + (lx, ly), result.points[1] + (rx, ry)]).astype(np.float32)
    write_npy(work_dir / "matches.npy", matches)
    artifacts["matches"] = str((work_dir / "matches.npy").relative_to(task.data_dir))
    metrics = {
        **result.metrics(),
        "match_scale": round(result.match_scale, 6),
        "left_box": list(split.left_box),
        "right_box": list(split.right_box),
        "gutter_x": split.gutter_x,
        "split_method": split.method,
        "split_confidence": split.confidence,
        "card_size": [int(card.shape[1]), int(card.shape[0])],
    }
    return StageOutput(outcome=result.outcome, reason=result.reason, metrics=metrics, artifacts=artifacts)
