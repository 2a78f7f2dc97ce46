"""The grade stage task: grade one card from its rectified views, disparity maps and earlier metrics."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..contracts import GradeInputs
from ..errors import PipelineError
from ..grading import GradeParams, grade, measure_card
from ..io import read_image, to_grey
from ..records import CardTask, param_hash
from ..results import CardResults
from .base import StageOutput, stage_task
from .spec import StageDeclaration, has_inputs

__all__ = ["STAGE", "TASK_INPUTS", "grade_inputs", "grade_task", "load_map"]

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


def grade_inputs(card: CardResults, approved: Mapping[str, Any]) -> GradeInputs:
    """What the grader measures: the rectified views, both disparity maps and their confidence
    (paths under the data dir), and the metrics of the filter, rectify and disparity results."""
    latest = card.latest_results()
    rectify, disparity = latest.get("rectify"), latest.get("disparity")
    if rectify is None or disparity is None or disparity.status != "done" or rectify.status == "failed":
        return {}
    return cast(
        GradeInputs,
        {
            "left": rectify.artifacts.get("left"),
            "right": rectify.artifacts.get("right"),
            "disparity_left": disparity.artifacts.get("disparity_left"),
            "disparity_right": disparity.artifacts.get("disparity_right"),
            "confidence": disparity.artifacts.get("confidence"),
            "metrics": {
                name: {k: v for k, v in result.metrics.items() if k != "inputs_digest"}
                for name, result in latest.items()
                if name in ("filter", "rectify", "disparity")
            },
            "disparity_param_hash": disparity.param_hash,
        },
    )


# Cards with a disparity: few / some artifacts / failure, with reasons in words. The thresholds
# are the newest fitted grade model's where review provides them (core.hooks.stage_params).
STAGE = StageDeclaration(
    name="grade",
    position=50,
    params=GradeParams,
    task=grade_task,
    eligible_states=("pass", "review"),
    inputs=grade_inputs,
    requires="disparity",
    ready=has_inputs,
    chains=True,
)
