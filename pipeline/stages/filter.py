"""The filter stage task: split the card at its gutter and route it by SIFT good-match fraction."""

from __future__ import annotations

from pathlib import Path

from ..filter import FilterParams, filter_card
from ..io import read_image, write_jpeg
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
    metrics = {
        **result.metrics(),
        "left_box": list(split.left_box),
        "right_box": list(split.right_box),
        "gutter_x": split.gutter_x,
        "split_method": split.method,
        "split_confidence": split.confidence,
        "card_size": [int(card.shape[1]), int(card.shape[0])],
    }
    return StageOutput(outcome=result.outcome, reason=result.reason, metrics=metrics, artifacts=artifacts)
