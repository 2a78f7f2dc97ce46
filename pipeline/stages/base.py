"""The one wrapper every stage task runs in: timing, parameter hash, typed error to failed record.

A stage task is a function ``(CardTask, params) -> StageRecord`` that workers run. Its body
(decorated with :func:`stage_task`) reads its inputs, calls the pure functions of its concept and
returns a :class:`StageOutput`; the wrapper adds what every record carries (card, stage, parameter
hash, start time, seconds, code version) and turns any exception into a ``failed`` record with a
typed reason, so one bad card never stops a batch.
"""

from __future__ import annotations

import functools
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from .. import CODE_VERSION
from ..errors import PipelineError
from ..records import CardTask, StageRecord, StageStatus, param_hash

__all__ = ["PREVIEW_MAX_SIDE", "StageOutput", "failure_reason", "stage_task"]

# Halves and views are stored as display previews at most this many px on their longer side
# (later stages read the original or the full-size artifacts): full-size PNG previews would
# cost ~1 MB a card, 250 GB for 250,000 cards.
PREVIEW_MAX_SIDE = 800

ParamsT = TypeVar("ParamsT")


@dataclass(frozen=True)
class StageOutput:
    """What a stage body decided for one card; :func:`stage_task` makes it a :class:`StageRecord`."""

    status: StageStatus = "done"
    outcome: str | None = None
    reason: str | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    artifacts: dict[str, str] = field(default_factory=dict)


def failure_reason(exc: Exception) -> str:
    """A typed reason for a stage's record: the error's own code, or ``internal_error`` for a
    bug or an OpenCV error on a strange card."""
    if isinstance(exc, PipelineError):
        return exc.reason()
    return f"internal_error: {traceback.format_exception_only(type(exc), exc)[-1].strip()}"


def stage_task(stage: str) -> Callable[[Callable[[CardTask, ParamsT], StageOutput]], Callable[[CardTask, ParamsT], StageRecord]]:
    """Decorate a stage body ``(task, params) -> StageOutput`` into the task workers run.

    The decorated function keeps the body's name and module, so ``functools.partial(task,
    params=...)`` pickles by reference for process pools and dask workers.
    """

    def wrap(body: Callable[[CardTask, ParamsT], StageOutput]) -> Callable[[CardTask, ParamsT], StageRecord]:
        @functools.wraps(body)
        def run(task: CardTask, params: ParamsT) -> StageRecord:
            started, clock = time.time(), time.perf_counter()
            phash = param_hash(params)
            try:
                output = body(task, params)
            except Exception as exc:  # noqa: BLE001 - one bad card never stops a batch: record why, go on
                return StageRecord(
                    card_id=task.card_id,
                    stage=stage,
                    param_hash=phash,
                    status="failed",
                    reason=failure_reason(exc),
                    started_at=started,
                    seconds=time.perf_counter() - clock,
                    code_version=CODE_VERSION,
                )
            return StageRecord(
                card_id=task.card_id,
                stage=stage,
                param_hash=phash,
                status=output.status,
                outcome=output.outcome,
                reason=output.reason,
                metrics=output.metrics,
                artifacts=output.artifacts,
                started_at=started,
                seconds=time.perf_counter() - clock,
                code_version=CODE_VERSION,
            )

        return run

    return wrap
