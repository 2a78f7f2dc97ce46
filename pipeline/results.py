"""A card's stage results as the input builders read them: a small protocol, not the database.

The builders that turn earlier results into a stage's inputs (``inputs`` of
:class:`pipeline.stages.spec.StageDeclaration`) run in the driver when it plans a stage, and in a
worker when it runs a stage chained after another (:mod:`pipeline.chains`). Both hand them an
object with a ``state`` and ``latest_results()``: the driver a ``core.models.Card`` row, a worker
a :class:`pipeline.chains.ChainCard` built from the driver's snapshot (:class:`ResultView`) and
the :class:`pipeline.records.StageRecord` s the chain has just made. Neither is imported here, so a
worker loads no database layer.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = ["FINISHED", "CardResults", "ResultView", "StageResultLike"]

# The statuses a stage's ``requires`` must have reached before the stage may run on a card (a
# skipped stage counts: the card did not need it).
FINISHED: tuple[str, ...] = ("done", "skipped")


class StageResultLike(Protocol):
    """One stage's latest result for a card: ``core.models.StageResult``, a
    :class:`pipeline.records.StageRecord` or a :class:`ResultView` (read-only, so each fits)."""

    @property
    def stage(self) -> str: ...

    @property
    def param_hash(self) -> str: ...

    @property
    def status(self) -> str: ...

    @property
    def outcome(self) -> str | None: ...

    @property
    def reason(self) -> str | None: ...

    @property
    def metrics(self) -> Mapping[str, Any]: ...

    @property
    def artifacts(self) -> Mapping[str, Any]: ...


class CardResults(Protocol):
    """A card as the input builders see it: its state (``ingested``, ``pass``, ``review``,
    ``culled``, ``failed``) and its latest result per stage, whatever the parameters."""

    @property
    def state(self) -> str: ...

    def latest_results(self) -> Mapping[str, StageResultLike]: ...


@dataclass(frozen=True)
class ResultView:
    """A stage result as plain values a worker can receive (the driver's snapshot of a row)."""

    stage: str
    param_hash: str
    status: str
    outcome: str | None
    metrics: dict[str, Any]
    artifacts: dict[str, str]
    reason: str | None = None
