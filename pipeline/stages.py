"""Per-card stage tasks: read the original, call the pure stage, write artifacts, return a record.

These are the functions workers run. Each catches everything a card can throw at it and
returns a ``failed`` record with a typed reason, so one bad card never stops a batch.
"""

from __future__ import annotations

import time
import traceback
from pathlib import Path

import numpy as np

from . import CODE_VERSION
from .errors import PipelineError
from .filter import FilterParams, filter_card
from .io import read_image, write_jpeg, write_json, write_png
from .records import CardTask, StageRecord, param_hash
from .rectify import RectifyParams, rectify_pair, warp_pair
from .split import CardSplit, crop_halves

# Halves are stored as display previews only (later stages crop the original with the
# recorded boxes): full-size PNG halves would cost ~1 MB a card, 250 GB for 250,000 cards.
PREVIEW_MAX_SIDE = 800


def filter_task(task: CardTask, params: FilterParams) -> StageRecord:
    """Split the card at its gutter and route it by SIFT good-match fraction."""
    started, clock = time.time(), time.perf_counter()
    phash = param_hash(params)
    try:
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
        return StageRecord(
            card_id=task.card_id, stage="filter", param_hash=phash, status="done", outcome=result.outcome,
            reason=result.reason, metrics=metrics, artifacts=artifacts, started_at=started,
            seconds=time.perf_counter() - clock, code_version=CODE_VERSION,
        )
    except PipelineError as exc:
        return _failed(task, "filter", phash, exc.reason(), started, clock)
    except Exception as exc:  # a bug or an OpenCV error on a strange card: record it, go on
        detail = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return _failed(task, "filter", phash, f"internal_error: {detail}", started, clock)


def rectify_task(task: CardTask, params: RectifyParams) -> StageRecord:
    """Rectify the card's two halves (Loop-Zhang with the paper's changes).

    ``task.inputs`` must hold the filter's ``left_box`` and ``right_box`` (card pixels). A pair
    already rectified within tolerance is recorded ``skipped`` with the reason, and its halves
    are stored unwarped so the disparity stage reads one place either way.
    """
    started, clock = time.time(), time.perf_counter()
    phash = param_hash(params)
    try:
        card = read_image(task.image_path)
        boxes = task.inputs.get("left_box"), task.inputs.get("right_box")
        if boxes[0] is None or boxes[1] is None:
            raise PipelineError("no split boxes from the filter stage; run the filter first")
        split = CardSplit(left_box=tuple(boxes[0]), right_box=tuple(boxes[1]), gutter_x=0, method="recorded",
                          confidence=1.0)
        left, right = (np.ascontiguousarray(half) for half in crop_halves(card, split))
        rect = rectify_pair(left, right, params)
        left_rect, right_rect = warp_pair(left, right, rect)
        work_dir = Path(task.work_dir)
        artifacts = {}
        for name, view in (("left", left_rect), ("right", right_rect)):
            write_png(work_dir / f"{name}.png", view)
            write_jpeg(work_dir / f"{name}_preview.jpg", view, max_side=PREVIEW_MAX_SIDE)
            artifacts[name] = str((work_dir / f"{name}.png").relative_to(task.data_dir))
            artifacts[f"{name}_preview"] = str((work_dir / f"{name}_preview.jpg").relative_to(task.data_dir))
        camera = work_dir / "rectification.json"
        write_json(camera, {
            "convention": "column vectors, x' ~ H x, pixels with the origin at the top-left pixel centre; "
                          "H_l/H_r map the cropped left/right halves (boxes in card pixels) to the rectified views; "
                          "disparity d = x_left - x_right >= 0",
            "left_box": list(boxes[0]), "right_box": list(boxes[1]), **rect.metrics(),
        })
        artifacts["rectification"] = str(camera.relative_to(task.data_dir))
        status = "done" if rect.warp_needed else "skipped"
        reason = None if rect.warp_needed else f"not needed: {rect.reason}"
        if rect.swapped:
            reason = (reason + "; " if reason else "") + "eyes were swapped on the card: halves exchanged"
        metrics = {k: v for k, v in rect.metrics().items() if k not in ("reason",)}
        return StageRecord(
            card_id=task.card_id, stage="rectify", param_hash=phash, status=status, reason=reason,
            metrics=metrics, artifacts=artifacts, started_at=started, seconds=time.perf_counter() - clock,
            code_version=CODE_VERSION,
        )
    except PipelineError as exc:
        return _failed(task, "rectify", phash, exc.reason(), started, clock)
    except Exception as exc:  # an OpenCV error on a strange card: record it, go on
        detail = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return _failed(task, "rectify", phash, f"internal_error: {detail}", started, clock)


def _failed(task: CardTask, stage: str, phash: str, reason: str, started: float, clock: float) -> StageRecord:
    return StageRecord(
        card_id=task.card_id, stage=stage, param_hash=phash, status="failed", reason=reason,
        started_at=started, seconds=time.perf_counter() - clock, code_version=CODE_VERSION,
    )
