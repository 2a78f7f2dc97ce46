"""The grade stage task: grade one card from its rectified views, disparity maps and earlier metrics."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PipelineError
from ..grading import GradeParams, grade, measure_card
from ..io import read_image, to_grey
from ..records import CardTask, param_hash
from .base import StageOutput, stage_task

__all__ = ["TASK_INPUTS", "grade_task", "load_map"]

TASK_INPUTS = ("left", "right", "disparity_left", "disparity_right", "confidence")


def load_map(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError as exc:
        raise PipelineError(f"no such file: {path}") from exc
    except (OSError, ValueError) as exc:
        raise PipelineError(f"cannot read {path.name}: {exc}") from exc


@stage_task("grade")
def grade_task(task: CardTask, params: GradeParams) -> StageOutput:
    """Grade one card from its rectified views, disparity maps and earlier stages' metrics.

    ``task.inputs``: ``left``, ``right`` (rectified views), ``disparity_left``,
    ``disparity_right``, ``confidence`` (``.npy``), all paths relative to ``task.data_dir``, and
    ``metrics`` = ``{"filter": {...}, "rectify": {...}, "disparity": {...}}``. The record's
    ``outcome`` is the grade, ``reason`` the reasons joined by "; " (the deciding one first),
    ``metrics`` the measurements plus ``reasons``, ``notes``, ``uncertainty``,
    ``uncertainty_reason``, ``deciding``, ``levels``, ``nearest`` (the measurement nearest a
    threshold: ``{"measurement", "value", "threshold", "margin", "level", ...}``), ``checks`` (one
    row per measurement, for a table; see :class:`pipeline.grading.GradeResult`) and
    ``thresholds_hash``. Measurements are in the rectified views' pixels. Any error gives a ``failed`` record with a typed reason.
    """
    missing = [name for name in TASK_INPUTS if not task.inputs.get(name)]
    if missing:
        raise PipelineError(f"missing inputs {', '.join(missing)}: run rectify and disparity first")
    data_dir = Path(task.data_dir)
    left = read_image(data_dir / task.inputs["left"])
    right = read_image(data_dir / task.inputs["right"])
    maps = {name: load_map(data_dir / task.inputs[name]) for name in ("disparity_left", "disparity_right", "confidence")}
    if left.ndim != right.ndim:  # one stored grey, the other RGB: compare them as grey
        left, right = to_grey(left), to_grey(right)
    measurements = measure_card(
        left, right, maps["disparity_left"], maps["disparity_right"], maps["confidence"], task.inputs.get("metrics") or {}
    )
    result = grade(measurements, params.thresholds)
    metrics = {
        **measurements.as_dict(),
        "reasons": list(result.reasons),
        "notes": list(result.notes),
        "uncertainty": result.uncertainty,
        "deciding": list(result.deciding),
        "levels": dict(result.levels),
        "nearest": result.nearest,
        "checks": list(result.checks),
        "uncertainty_reason": result.uncertainty_reason,
        "thresholds_hash": param_hash(params.thresholds),
    }
    return StageOutput(status="done", outcome=result.grade, reason="; ".join(result.reasons), metrics=metrics)
