"""Per-card stage tasks: read the original, call the pure stage, write artifacts, return a record.

These are the functions workers run. Each catches everything a card can throw at it and
returns a ``failed`` record with a typed reason, so one bad card never stops a batch.
"""

from __future__ import annotations

import time
import traceback
from pathlib import Path

from . import CODE_VERSION
from .errors import PipelineError
from .filter import FilterParams, filter_card
from .io import read_image, write_jpeg
from .records import CardTask, StageRecord, param_hash
from .split import crop_halves

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


def _failed(task: CardTask, stage: str, phash: str, reason: str, started: float, clock: float) -> StageRecord:
    return StageRecord(
        card_id=task.card_id, stage=stage, param_hash=phash, status="failed", reason=reason,
        started_at=started, seconds=time.perf_counter() - clock, code_version=CODE_VERSION,
    )
