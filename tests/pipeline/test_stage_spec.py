"""Stages declare themselves (pipeline/stages/spec.py): the catalogue is every module of
pipeline/stages with a ``STAGE``, in flow order, with its wiring checked when it is built."""

from __future__ import annotations

import pickle
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import pipeline.stages
from pipeline.records import param_hash
from pipeline.stages.spec import (
    PEOPLE_STAGES,
    StageDeclaration,
    StageDeclarationError,
    declared_stages,
    flow_stages,
)
from pipeline.view_synthesis import ViewsStageParams

# The default parameters' hashes when the stages came to declare themselves (the same as the
# hand-written catalogue's before): results are keyed by them, so a changed hash reruns every
# card. Change one only on purpose, with the parameters.
DEFAULT_PARAM_HASHES = {
    "filter": "ec9a01f87d6ce0fb",
    "orientation": "946784977d3801e8",
    "rectify": "72dae130e5c31280",
    "disparity": "73fd92251f9f8cad",
    "grade": "477bb351cf48da7f",
    "views": "83d008e078c10fcc",
}

TOY_STAGE = """
from dataclasses import dataclass

from pipeline.stages.base import StageOutput, stage_task
from pipeline.stages.spec import StageDeclaration


@dataclass(frozen=True)
class ToyParams:
    level: int = 1


@stage_task("{name}")
def toy_task(task, params):
    return StageOutput(outcome="toy")


STAGE = StageDeclaration(
    name="{name}", position={position}, params=ToyParams, task=toy_task, eligible_states=("pass",), requires={requires!r}
)
"""


@pytest.fixture
def stage_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., None]]:
    """``stage_module(module, name=..., position=..., requires=...)`` adds a module to
    pipeline.stages (from a folder added to the package's path) for one test."""
    monkeypatch.setattr(pipeline.stages, "__path__", [*pipeline.stages.__path__, str(tmp_path)])
    added: list[str] = []

    def add(module: str, *, name: str, position: int, requires: str | None = None) -> None:
        (tmp_path / f"{module}.py").write_text(TOY_STAGE.format(name=name, position=position, requires=requires))
        added.append(f"pipeline.stages.{module}")

    yield add
    for module in added:
        sys.modules.pop(module, None)


def test_every_stage_module_declares_its_stage_in_flow_order() -> None:
    stages = declared_stages()
    assert list(stages) == ["filter", "orientation", "rectify", "disparity", "grade", "views"]
    for name, declaration in stages.items():
        assert declaration.task.__module__ == f"pipeline.stages.{name}"
    assert [name for name, d in stages.items() if d.chains] == ["orientation", "disparity", "grade", "views"]
    assert {name: d.keystone_run for name, d in stages.items() if d.keystone_run != "default"} == {"views": "on_request"}


def test_the_declared_default_parameters_hash_as_before() -> None:
    assert {name: param_hash(d.params()) for name, d in declared_stages().items()} == DEFAULT_PARAM_HASHES


def test_the_flow_places_peoples_stages_among_the_declared_ones() -> None:
    assert flow_stages() == ("filter", "orientation", "judge", "crop", "rectify", "disparity", "grade", "review", "views")
    assert not set(PEOPLE_STAGES) & set(declared_stages())


def test_config_fields_are_set_on_the_parameters() -> None:
    views = declared_stages()["views"]
    configured = views.configured(views.params(), {"KEYSTONE_INPAINT_CHECKPOINT": "/models/fill.pt"})
    assert configured == ViewsStageParams(checkpoint="/models/fill.pt")
    # Unset in the config: None, the default, so the hash is the default's.
    assert param_hash(views.configured(views.params(), {})) == DEFAULT_PARAM_HASHES["views"]
    grade = declared_stages()["grade"]
    params = grade.params()
    assert grade.configured(params, {"KEYSTONE_INPAINT_CHECKPOINT": "/x"}) is params  # declares no config field


def test_a_spec_binds_its_parameters_and_pickles_for_a_worker() -> None:
    declaration = declared_stages()["orientation"]
    params = declaration.params()
    spec = declaration.spec(params)
    assert spec.params is params and spec.task.keywords == {"params": params}  # type: ignore[attr-defined]
    assert (spec.inputs, spec.requires, spec.ready, spec.chains) == (
        declaration.inputs,
        declaration.requires,
        declaration.ready,
        True,
    )
    again = pickle.loads(pickle.dumps(spec))
    assert again.name == "orientation" and again.inputs is declaration.inputs and again.params == params


def test_a_new_module_in_the_package_is_a_new_stage_in_its_place(stage_module: Callable[..., None]) -> None:
    stage_module("toy", name="toy", position=45, requires="disparity")
    stages = declared_stages()
    assert list(stages) == ["filter", "orientation", "rectify", "disparity", "toy", "grade", "views"]
    assert isinstance(stages["toy"], StageDeclaration) and stages["toy"].keystone_run == "default"
    assert flow_stages().index("toy") == flow_stages().index("disparity") + 1


def test_two_modules_declaring_one_stage_is_a_wiring_error(stage_module: Callable[..., None]) -> None:
    stage_module("second_filter", name="filter", position=11)
    with pytest.raises(StageDeclarationError, match="two stage modules declare the stage 'filter'"):
        declared_stages()


def test_requiring_a_stage_declared_later_is_a_wiring_error(stage_module: Callable[..., None]) -> None:
    stage_module("too_early", name="too_early", position=5, requires="grade")
    with pytest.raises(StageDeclarationError, match="requires 'grade', which is not a stage declared before it"):
        declared_stages()
