"""The driver's catalogue is built from the stage modules' declarations: a module added to
pipeline/stages is a stage ``keystone run`` plans, chains and runs, with parameters a feature
or the app's config may set (runs/specs.py)."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

import pipeline.stages
from app.cli import cli
from core.hooks import stage_hooks
from pipeline.records import param_hash

# A whole new stage, as the how-to in docs/ARCHITECTURE.md writes one: the mean brightness of the
# left photo, from the filter's split boxes, chained after the filter and run only when named.
BRIGHTNESS_MODULE = '''
"""The brightness stage: the mean grey level of the card's left photo."""

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pipeline.io import read_image
from pipeline.records import CardTask
from pipeline.results import CardResults
from pipeline.stages.base import StageOutput, stage_task
from pipeline.stages.filter import filter_boxes
from pipeline.stages.spec import StageDeclaration, has_inputs


@dataclass(frozen=True)
class BrightnessParams:
    scale: float = 1.0
    label: str | None = None


def brightness_inputs(card: CardResults, approved: Mapping[str, Any]) -> dict[str, Any]:
    boxes = filter_boxes(card)
    return {"left_box": boxes["left_box"]} if boxes else {}


@stage_task("brightness")
def brightness_task(task: CardTask, params: BrightnessParams) -> StageOutput:
    x0, y0, x1, y1 = task.inputs["left_box"]
    grey = float(read_image(task.image_path)[y0:y1, x0:x1].mean())
    return StageOutput(outcome=params.label or "measured", metrics={"brightness": round(grey * params.scale, 3)})


STAGE = StageDeclaration(
    name="brightness",
    position=15,
    params=BrightnessParams,
    task=brightness_task,
    eligible_states=("pass", "review"),
    inputs=brightness_inputs,
    requires="filter",
    ready=has_inputs,
    chains=True,
    keystone_run="on_request",
    params_from_config={"label": "KEYSTONE_BRIGHTNESS_LABEL"},
)
'''


@pytest.fixture
def brightness_stage(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """The brightness module in a folder on pipeline.stages' path, for this test only."""
    folder = tmp_path / "more_stages"
    folder.mkdir()
    (folder / "brightness.py").write_text(BRIGHTNESS_MODULE)
    monkeypatch.setattr(pipeline.stages, "__path__", [*pipeline.stages.__path__, str(folder)])
    yield
    sys.modules.pop("pipeline.stages.brightness", None)


@pytest.fixture
def two_cards(tmp_path: Path, runner: Any, card_image: Any) -> None:
    """A stereo card the filter passes and a blank one it does not."""
    folder = tmp_path / "scans"
    folder.mkdir()
    Image.fromarray(card_image()).save(folder / "stereo.png")
    Image.fromarray(np.full((300, 800, 3), 128, np.uint8)).save(folder / "blank.png")
    result = runner.invoke(cli, ["ingest", str(folder), "--json"])
    assert result.exit_code == 0, result.output


def _run(runner: Any, *args: str) -> dict[str, dict[str, Any]]:
    result = runner.invoke(cli, ["run", "--json", *args])
    assert result.exit_code in (0, 1), result.output  # the blank card may fail the filter
    return {report["stage"]: report for report in json.loads(result.stdout)["stages"]}


def _brightness(runner: Any) -> dict[str, dict[str, Any]]:
    result = runner.invoke(cli, ["cards", "--json"])
    assert result.exit_code == 0, result.output
    return {card["source"]: card["stages"]["brightness"] for card in json.loads(result.stdout)["cards"]}


def test_a_stage_module_added_to_the_package_is_planned_chained_and_run(app, runner, brightness_stage, two_cards):  # type: ignore[no-untyped-def]
    from runs.specs import available_stages, default_run_stages, runnable_stages

    assert "brightness" in runnable_stages() and "brightness" not in default_run_stages()  # run only when named
    first = _run(runner, "--stages", "filter,brightness")
    assert list(first) == ["filter", "brightness"]
    # The stereo card only (the blank one is not passed): chained after the filter in the worker.
    assert first["brightness"]["processed"] == 1 and first["brightness"]["chained"] == 1
    assert first["brightness"]["outcomes"] == {"measured": 1}
    statuses = _brightness(runner)
    assert statuses["stereo.png"]["status"] == "done" and statuses["stereo.png"]["metrics"]["brightness"] > 0
    assert statuses["blank.png"]["status"] == "pending"

    again = _run(runner, "--stages", "filter,brightness")
    assert again["brightness"]["processed"] == 0 and again["brightness"]["already_done"] == 1
    with app.app_context():
        assert available_stages()["brightness"].params.label is None


def test_a_new_stages_parameters_come_from_a_feature_and_the_config(app, runner, brightness_stage, two_cards):  # type: ignore[no-untyped-def]
    from runs.specs import available_stages

    first = _run(runner, "--stages", "filter,brightness")
    measured = _brightness(runner)["stereo.png"]["metrics"]["brightness"]
    brightness = sys.modules["pipeline.stages.brightness"]
    # A feature provides the stage's parameters by name (as review does the grade thresholds) and
    # the config sets the declared field on top: new parameters, a new hash, the card runs again.
    stage_hooks(app).stage_params["brightness"] = lambda: brightness.BrightnessParams(scale=2.0)
    app.config["KEYSTONE_BRIGHTNESS_LABEL"] = "bright"
    with app.app_context():
        params = available_stages()["brightness"].params
    assert params == brightness.BrightnessParams(scale=2.0, label="bright")
    second = _run(runner, "--stages", "filter,brightness")
    assert second["brightness"]["param_hash"] == param_hash(params) != first["brightness"]["param_hash"]
    assert second["brightness"]["processed"] == 1 and second["brightness"]["outcomes"] == {"bright": 1}
    assert _brightness(runner)["stereo.png"]["metrics"]["brightness"] == pytest.approx(2 * measured, abs=0.002)
    assert second["brightness"]["chained"] == 0  # the filter was done already: it ran on its own turn
