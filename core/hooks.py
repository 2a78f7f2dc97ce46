"""What the run driver needs from the features, registered by the features themselves.

The driver (:mod:`runs.loop`) sits below the features: it must not import ``annotation`` or
``review``. Instead each feature, when its blueprint is registered on the app, tells the app
what a run needs from it:

* ``decisions``: people's approved decisions that feed stage inputs, per card and kind
  (the crowd's approved judge and crop aggregates): ``provider(card_ids) -> {card: {kind: obj}}``;
* ``people_work``: everything people did or are doing on a card, for its status
  (crowd aggregates in any state, the curator review), same shape;
* ``stage_params``: parameters a stage takes from a feature's data (the grade thresholds of
  the newest fitted grade model): ``provider() -> params``;
* ``after_write``: what must follow the driver's write of a stage's results (review's sync of
  new grades into the curators' queue): ``hook(card_ids) -> None``;
* ``change_marks``: a cheap value that moves when a feature's people decide something the
  audit trail does not record (the crowd's aggregates), so the background worker
  (:mod:`runs.worker`) knows to run again: ``mark() -> hashable``.

Providers merge in registration order; a later provider's kind overrides an earlier one's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from flask import Flask, current_app

CardProvider = Callable[[list[int]], dict[int, dict[str, Any]]]

EXTENSION_KEY = "keystone.stage_hooks"


@dataclass
class StageHooks:
    decisions: list[CardProvider] = field(default_factory=list)
    people_work: list[CardProvider] = field(default_factory=list)
    stage_params: dict[str, Callable[[], Any]] = field(default_factory=dict)
    after_write: dict[str, list[Callable[[list[int]], None]]] = field(default_factory=dict)
    change_marks: list[Callable[[], Any]] = field(default_factory=list)


def stage_hooks(app: Flask | None = None) -> StageHooks:
    """The app's registry (created empty on first use)."""
    target = app if app is not None else current_app
    hooks = target.extensions.get(EXTENSION_KEY)
    if hooks is None:
        hooks = target.extensions[EXTENSION_KEY] = StageHooks()
    return hooks


def merged(providers: list[CardProvider], card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """Every provider's answer for ``card_ids``, merged per card."""
    result: dict[int, dict[str, Any]] = {}
    if not card_ids:
        return result
    for provider in providers:
        for card_id, kinds in provider(card_ids).items():
            result.setdefault(card_id, {}).update(kinds)
    return result


def approved_decisions(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """People's approved decisions per card, as the features registered them: the crowd's
    approved judge, confirm and crop aggregates, a curator's orientation override and the
    operator's word for the card's collection, ``{card: {"judge": .., "crop": .., "confirm": ..,
    "orientation_override": .., "operator_orientation": ..}}``."""
    return merged(stage_hooks().decisions, card_ids)


def people_work(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    return merged(stage_hooks().people_work, card_ids)


def stage_params(stage: str, default: Callable[[], Any]) -> Any:
    """The parameters a feature provides for ``stage``, else ``default()``."""
    provider = stage_hooks().stage_params.get(stage)
    return provider() if provider is not None else default()


def after_write(stage: str, card_ids: list[int]) -> None:
    for hook in stage_hooks().after_write.get(stage, ()):
        hook(card_ids)
