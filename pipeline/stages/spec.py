"""What a stage declares about itself, and the catalogue built from those declarations.

Each stage module in this package ends with one module-level ``STAGE = StageDeclaration(...)``:
its name, where it sits in the flow, its default parameters, its task, which cards it applies to,
how its inputs are built from the card's earlier results and people's decisions, when a card is
ready for it, whether a worker may run it chained after the stage before it, and whether
``keystone run`` runs it. :func:`declared_stages` finds them (every module of the package that
has a ``STAGE``), so adding a stage is adding a module; the driver (``runs.specs``) resolves each
declaration's parameters (a feature's, the app's config) into a :class:`StageSpec` and runs those.

Wiring errors (two stages of one name, a ``requires`` that names no earlier stage) raise :class:`StageDeclarationError` when the catalogue is
built, before any card runs.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import pkgutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Generic, Literal, TypeVar

from ..records import CardTask, StageRecord
from ..results import CardResults

__all__ = [
    "InputsBuilder",
    "ReadyCheck",
    "StageDeclaration",
    "StageDeclarationError",
    "PEOPLE_STAGES",
    "StageSpec",
    "declared_stages",
    "flow_stages",
    "has_inputs",
]

ParamsT = TypeVar("ParamsT")

# (card, people's approved decisions about it) -> the stage's inputs (plain JSON values). The
# decisions are a mapping of kind -> value (see ``core.hooks.approved_decisions``); a worker
# running a chained stage gets only the plain collection-wide ones (:class:`pipeline.chains.ChainTask`).
InputsBuilder = Callable[[CardResults, Mapping[str, Any]], Mapping[str, Any]]
# (card, its inputs) -> whether the stage can run on it now.
ReadyCheck = Callable[[CardResults, dict[str, Any]], bool]
# How ``keystone run`` treats a stage: in its default ``--stages``, only when named, or never.
KeystoneRun = Literal["default", "on_request", "never"]


# The stages that are people's work (the crowd's judge and crop tasks in annotation/, the curators'
# review in review/): no module here declares them, and the driver never runs them, but a card's
# status lists them in their place in the flow (``position``, as the declarations').
PEOPLE_STAGES: dict[str, int] = {"judge": 22, "crop": 24, "review": 55}


class StageDeclarationError(ValueError):
    """The stage declarations do not fit together (found when the catalogue is built)."""


@dataclass(frozen=True)
class StageSpec:
    """A stage ready to run: its declaration with the parameters resolved and bound to the task.

    Pickled by value into chains (:mod:`pipeline.chains`), so every field is a plain value or a
    module-level function (pickled by reference)."""

    name: str
    params: Any
    task: Callable[[CardTask], StageRecord]
    # The card states this stage applies to; other cards are not its business.
    eligible_states: tuple[str, ...]
    # What earlier stages (and approved crowd annotations) decided that this one needs.
    # The builders return the TypedDicts of pipeline.contracts (RectifyInputs, GradeInputs, ...).
    inputs: InputsBuilder | None = None
    # The stage whose latest result must be done or skipped before this one can run.
    requires: str | None = None
    # Given a card and its inputs, whether it can run now (e.g. a card the filter sent to
    # review waits until the crowd has judged it a stereo pair).
    ready: ReadyCheck | None = None
    # Its inputs come from the card's own stage results alone (no people's decisions), so a
    # worker may run it on a card right after the stage before it in the run (pipeline.chains).
    chains: bool = False
    # Of people's approved decisions about a card, those its inputs builder reads, as plain
    # values (no database rows): what the driver sends a worker that runs this stage chained
    # (pipeline.chains.ChainTask.approved). The builder must read its own output back unchanged.
    plain_decisions: Callable[[Mapping[str, Any]], dict[str, Any]] | None = None


@dataclass(frozen=True)
class StageDeclaration(Generic[ParamsT]):
    """What one stage module says about its stage (``STAGE = StageDeclaration(...)``)."""

    name: str
    # Where the stage sits in the flow: the catalogue and ``keystone run`` order stages by it.
    # The built-in stages use multiples of 10 (filter 10 ... views 60), so a new one fits between.
    position: int
    # The default parameters (a frozen dataclass: its param_hash keys the stage's results).
    params: Callable[[], ParamsT]
    # The task body decorated by :func:`pipeline.stages.base.stage_task`, ``(task, params) -> record``.
    task: Callable[[CardTask, ParamsT], StageRecord]
    eligible_states: tuple[str, ...]
    inputs: InputsBuilder | None = None
    requires: str | None = None
    ready: ReadyCheck | None = None
    chains: bool = False
    plain_decisions: Callable[[Mapping[str, Any]], dict[str, Any]] | None = None
    keystone_run: KeystoneRun = "default"
    # Parameter fields the app's config sets when a run starts: field -> config key (the views
    # stage's ``checkpoint`` from ``KEYSTONE_INPAINT_CHECKPOINT``). A feature may instead provide
    # the whole parameters through ``core.hooks`` (``stage_params``, by stage name: the fitted
    # grade thresholds); the config's fields are then set on what the feature gave.
    params_from_config: Mapping[str, str] = field(default_factory=dict)

    def configured(self, params: ParamsT, config: Mapping[str, Any]) -> ParamsT:
        """``params`` with the fields of :attr:`params_from_config` taken from ``config``
        (a missing key gives None, as ``config.get`` does)."""
        if not self.params_from_config:
            return params
        changes = {name: config.get(key) for name, key in self.params_from_config.items()}
        return dataclasses.replace(params, **changes)  # type: ignore[type-var]

    def spec(self, params: ParamsT) -> StageSpec:
        """The stage with these parameters, its task bound to them (a ``functools.partial`` of a
        module-level function: it pickles by reference for process pools and dask workers)."""
        return StageSpec(
            name=self.name,
            params=params,
            # By keyword, as every stage's body names it (a Callable type cannot say so).
            task=functools.partial(self.task, params=params),  # type: ignore[call-arg]
            eligible_states=self.eligible_states,
            inputs=self.inputs,
            requires=self.requires,
            ready=self.ready,
            chains=self.chains,
            plain_decisions=self.plain_decisions,
        )


def has_inputs(card: CardResults, inputs: dict[str, Any]) -> bool:
    """The ``ready`` of a stage that can run once its builder found anything to build from."""
    return bool(inputs)


def _stage_modules(package: ModuleType) -> list[ModuleType]:
    return [importlib.import_module(f"{package.__name__}.{info.name}") for info in pkgutil.iter_modules(package.__path__)]


def declared_stages() -> dict[str, StageDeclaration[Any]]:
    """Every stage declared by a module of :mod:`pipeline.stages`, in flow order (``position``).

    Imports each module of the package (the stage tasks load numpy, OpenCV and scipy, never torch
    at import time). Raises :class:`StageDeclarationError` on a wiring error."""
    from .. import stages

    found: list[StageDeclaration[Any]] = []
    for module in _stage_modules(stages):
        declaration = getattr(module, "STAGE", None)
        if isinstance(declaration, StageDeclaration):
            found.append(declaration)
    found.sort(key=lambda declaration: (declaration.position, declaration.name))
    catalogue: dict[str, StageDeclaration[Any]] = {}
    for declaration in found:
        if declaration.name in catalogue:
            raise StageDeclarationError(f"two stage modules declare the stage {declaration.name!r}")
        if declaration.requires is not None and declaration.requires not in catalogue:
            raise StageDeclarationError(
                f"stage {declaration.name!r} requires {declaration.requires!r}, which is not a stage declared before it"
            )
        catalogue[declaration.name] = declaration
    return catalogue


def flow_stages() -> tuple[str, ...]:
    """Every stage of a card's flow, the declared ones and people's (:data:`PEOPLE_STAGES`), in
    flow order: what ``keystone cards`` reports a status for."""
    positions = {name: declaration.position for name, declaration in declared_stages().items()} | PEOPLE_STAGES
    return tuple(sorted(positions, key=lambda name: (positions[name], name)))
