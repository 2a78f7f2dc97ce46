"""The typed stage records (pipeline.contracts) name exactly what the stages write and what the
run driver builds: filter, rectify and disparity run on a real pair (Middlebury's Motorcycle,
scaled down), the input builders the stage modules declare turn their records into the next
stage's inputs."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from skimage import data

from pipeline.contracts import (
    DisparityInputs,
    DisparityMetrics,
    FilterMetrics,
    GradeInputs,
    RectifyInputs,
    RectifyMetrics,
    ViewsInputs,
)
from pipeline.filter import FilterParams
from pipeline.io import write_png
from pipeline.records import CardTask
from pipeline.rectify import RectifyParams
from pipeline.stages.disparity import DisparityStageParams, disparity_task
from pipeline.stages.filter import filter_task
from pipeline.stages.rectify import rectify_task
from pipeline.stages.spec import declared_stages


def _keys(contract: Any) -> set[str]:
    return set(contract.__optional_keys__) | set(contract.__required_keys__)


@pytest.fixture(scope="module")
def records(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("contracts")
    left, right, _ = data.stereo_motorcycle()
    left, right = (cv2.resize(v, (v.shape[1] // 2, v.shape[0] // 2), interpolation=cv2.INTER_AREA) for v in (left, right))
    h, w = left.shape[:2]
    card = np.full((h + 40, 2 * w + 60, 3), 200, np.uint8)
    card[20 : 20 + h, 20 : 20 + w], card[20 : 20 + h, w + 40 : 2 * w + 40] = left, right
    write_png(root / "card.png", card)

    def task(stage: str, inputs: dict[str, Any]) -> CardTask:
        (root / stage).mkdir()
        return CardTask(
            card_id=1,
            content_hash="x",
            image_path=str(root / "card.png"),
            work_dir=str(root / stage),
            data_dir=str(root),
            inputs=inputs,
        )

    found = {"filter": filter_task(task("filter", {}), FilterParams())}
    assert found["filter"].status == "done", found["filter"].reason
    found["rectify"] = rectify_task(
        task("rectify", {k: found["filter"].metrics[k] for k in ("left_box", "right_box")}), RectifyParams()
    )
    assert found["rectify"].status in ("done", "skipped"), found["rectify"].reason
    found["disparity"] = disparity_task(task("disparity", _stage_inputs("disparity", found)), DisparityStageParams())
    assert found["disparity"].status == "done", found["disparity"].reason
    return found


def _card(found: dict[str, Any]) -> Any:
    """A stand-in for core.models.Card as the input builders read it: the latest result per stage."""
    results = {
        stage: SimpleNamespace(
            stage=stage, status=r.status, outcome=r.outcome, metrics=r.metrics, artifacts=r.artifacts, param_hash=r.param_hash
        )
        for stage, r in found.items()
    }
    return SimpleNamespace(state="pass", latest_results=lambda: results)


def _stage_inputs(stage: str, found: dict[str, Any]) -> dict[str, Any]:
    """The inputs the stage's declared builder makes from these records (no people's decisions)."""
    builder = declared_stages()[stage].inputs
    assert builder is not None
    return dict(builder(_card(found), {}))


def test_the_metrics_contracts_name_every_key_the_stages_write(records: dict[str, Any]) -> None:
    assert set(records["filter"].metrics) == _keys(FilterMetrics)
    assert set(records["rectify"].metrics) == _keys(RectifyMetrics)
    assert set(records["disparity"].metrics) == _keys(DisparityMetrics)


def test_the_input_contracts_name_every_key_the_driver_builds(records: dict[str, Any]) -> None:
    rectify = _stage_inputs("rectify", records)
    assert set(rectify) <= _keys(RectifyInputs) and {"left_box", "right_box", "box_source"} <= set(rectify)
    assert set(_stage_inputs("disparity", records)) == _keys(DisparityInputs)
    grade = _stage_inputs("grade", records)
    assert set(grade) == _keys(GradeInputs) and set(grade["metrics"]) == {"filter", "rectify", "disparity"}
    graded = {**records, "grade": SimpleNamespace(status="done", outcome="few", metrics={}, artifacts={}, param_hash="g")}
    assert set(_stage_inputs("views", graded)) == _keys(ViewsInputs) - {"depth"}
