"""The filter stage task: split the card at its gutter and route it by SIFT good-match fraction."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..filter import FilterParams, decode_width, filter_card
from ..io import read_image_reduced, write_jpeg, write_npy
from ..records import CardTask
from ..results import CardResults
from ..split import crop_halves, scale_split
from .base import PREVIEW_MAX_SIDE, StageOutput, stage_task
from .spec import StageDeclaration

__all__ = ["STAGE", "filter_boxes", "filter_task"]


@stage_task("filter")
def filter_task(task: CardTask, params: FilterParams) -> StageOutput:
    """Split the card at its gutter and route it by SIFT good-match fraction.

    A large JPEG scan is decoded at a reduced size (``params.reduced_decode``,
    :func:`pipeline.filter.decode_width`); the boxes, gutter and matches recorded are in the full
    card's pixels whatever the decode, and the halves' previews are cut from the decoded copy."""
    min_width = decode_width(params) if params.reduced_decode else 10**9
    decoded = read_image_reduced(task.image_path, (min_width, 1))
    card = decoded.pixels
    found, result = filter_card(card, params)
    left, right = crop_halves(card, found)
    split = scale_split(found, decoded.factor, decoded.full_size)
    work_dir = Path(task.work_dir)
    artifacts = {}
    for name, half in (("left", left), ("right", right)):
        target = work_dir / f"{name}.jpg"
        write_jpeg(target, half, max_side=PREVIEW_MAX_SIDE)
        artifacts[name] = str(target.relative_to(task.data_dir))
    # The good matches in card px, (N, 4) [x_left, y_left, x_right, y_right]: the rectify stage
    # aligns the crops and rectifies from them instead of running SIFT on the photos again.
    (lx, ly), (rx, ry) = found.left_box[:2], found.right_box[:2]
    matches = np.hstack([decoded.to_full(result.points[0] + (lx, ly)), decoded.to_full(result.points[1] + (rx, ry))]).astype(
        np.float32
    )
    write_npy(work_dir / "matches.npy", matches)
    artifacts["matches"] = str((work_dir / "matches.npy").relative_to(task.data_dir))
    metrics = {
        **result.metrics(),
        "match_scale": round(result.match_scale * decoded.factor, 6),  # full card px per SIFT px
        "decode_factor": decoded.factor,
        "left_box": list(split.left_box),
        "right_box": list(split.right_box),
        "gutter_x": split.gutter_x,
        "split_method": split.method,
        "split_confidence": split.confidence,
        "card_size": list(decoded.full_size),
    }
    return StageOutput(outcome=result.outcome, reason=result.reason, metrics=metrics, artifacts=artifacts)


def filter_boxes(card: CardResults) -> dict[str, Any]:
    """The split boxes of the card's latest filter result (what the orientation step and
    rectification start from)."""
    result = card.latest_results().get("filter")
    if result is None or result.status != "done":
        return {}
    return {
        "left_box": result.metrics.get("left_box"),
        "right_box": result.metrics.get("right_box"),
        "box_source": f"filter split ({result.param_hash})",
        # The filter's SIFT matches, reused by rectification (card px, and card px per SIFT px).
        "filter_matches": result.artifacts.get("matches"),
        "filter_match_scale": result.metrics.get("match_scale"),
    }


# Every card, whatever the filter decided before: a rerun with new parameters may route it anew.
STAGE = StageDeclaration(
    name="filter",
    position=10,
    params=FilterParams,
    task=filter_task,
    eligible_states=("ingested", "pass", "review", "culled", "failed"),
)
