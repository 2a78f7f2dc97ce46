"""A stage that reports what its worker process has imported, for tests/pipeline/test_chains_in_workers.py.

Kept out of the test module so that a worker unpickling it imports this small module (stdlib and
``pipeline`` only), not pytest's test module and whatever that imports.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pipeline.decided_orientation import card_orientation
from pipeline.records import CardTask
from pipeline.results import CardResults
from pipeline.stages.base import StageOutput, stage_task
from pipeline.stages.filter import filter_boxes
from pipeline.stages.orientation import photo_area_boxes
from pipeline.stages.spec import StageDeclaration

# Top-level packages a worker must not load: the web stack, the database layer, the CLI library,
# and every product package above pipeline/.
FORBIDDEN = ("flask", "sqlalchemy", "click", "app", "core", "runs", "catalogue", "annotation", "review", "exports")


def forbidden_loaded() -> list[str]:
    """The forbidden packages this process has imported (top-level names)."""
    return sorted({name.split(".")[0] for name in sys.modules} & set(FORBIDDEN))


@dataclass(frozen=True)
class ProbeParams:
    version: int = 1


def probe_inputs(card: CardResults, approved: Mapping[str, Any]) -> dict[str, Any]:
    """Builds its inputs as the real builders do, from the chain's snapshot and fresh records."""
    return {"orientation": card_orientation(card, approved), "boxes": photo_area_boxes(card) or filter_boxes(card)}


@stage_task("probe")
def probe_task(task: CardTask, params: ProbeParams) -> StageOutput:
    return StageOutput(metrics={"forbidden_loaded": forbidden_loaded(), "pid": os.getpid(), "inputs": task.inputs})


PROBE = StageDeclaration(
    name="probe",
    position=25,
    params=ProbeParams,
    task=probe_task,
    eligible_states=("pass", "review"),
    inputs=probe_inputs,
    requires="orientation",
    chains=True,
)
