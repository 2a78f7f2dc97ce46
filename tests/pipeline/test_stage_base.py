"""The one wrapper every stage task runs in (pipeline.stages.base)."""

from __future__ import annotations

import functools
import pickle
from dataclasses import dataclass

import pytest

from pipeline import CODE_VERSION
from pipeline.errors import InvalidInputError
from pipeline.filter import FilterParams
from pipeline.records import CardTask, param_hash
from pipeline.stages.base import StageOutput, failure_reason, stage_task
from pipeline.stages.filter import filter_task


@dataclass(frozen=True)
class EchoParams:
    fail_with: str = ""


@stage_task("echo")
def echo_task(task: CardTask, params: EchoParams) -> StageOutput:
    if params.fail_with == "typed":
        raise InvalidInputError("the card is blank")
    if params.fail_with == "bug":
        raise ZeroDivisionError("division by zero")
    return StageOutput(status="skipped", reason="not needed: nothing to echo", metrics={"inputs": dict(task.inputs)})


TASK = CardTask(card_id=7, content_hash="ab", image_path="/nowhere.png", work_dir="/tmp", data_dir="/tmp", inputs={"x": 1})


def test_a_body_output_becomes_a_record_with_what_every_record_carries():
    record = echo_task(TASK, EchoParams())
    assert (record.card_id, record.stage, record.status) == (7, "echo", "skipped")
    assert record.reason == "not needed: nothing to echo" and record.metrics == {"inputs": {"x": 1}}
    assert record.param_hash == param_hash(EchoParams()) and record.code_version == CODE_VERSION
    assert record.seconds >= 0 and record.started_at > 1.7e9


@pytest.mark.parametrize(
    ("fail_with", "reason"),
    [
        ("typed", "invalid_input: the card is blank"),
        ("bug", "internal_error: ZeroDivisionError: division by zero"),
    ],
)
def test_an_exception_becomes_a_failed_record_with_a_typed_reason(fail_with, reason):
    record = echo_task(TASK, EchoParams(fail_with=fail_with))
    assert record.status == "failed" and record.reason == reason
    assert record.param_hash == param_hash(EchoParams(fail_with=fail_with)) and record.metrics == {}


def test_failure_reason_names_the_error_class_for_a_bug():
    assert failure_reason(KeyError("left")) == "internal_error: KeyError: 'left'"


def test_a_stage_task_pickles_by_reference_for_process_pools_and_dask():
    bound = functools.partial(filter_task, params=FilterParams())
    restored = pickle.loads(pickle.dumps(bound))
    assert restored.func is filter_task
    record = restored(TASK)  # the image does not exist: a typed failure, not an exception
    assert record.status == "failed" and record.stage == "filter"
    assert record.reason.startswith("unreadable_image:")
