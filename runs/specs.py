"""The driver's stage catalogue: every stage a module of ``pipeline/stages/`` declares
(:func:`pipeline.stages.spec.declared_stages`), with its parameters resolved for this app.

A stage's parameters are its declaration's defaults, unless a feature provides them through
``core.hooks.stage_params`` (review: the thresholds of the newest fitted grade model), with the
fields the declaration takes from the app's config set on top (``params_from_config``: the views
stage's inpainting checkpoint). The input builders live with their stages, in ``pipeline/``, so a
worker that runs a stage chained after another imports no web or database layer.
"""

from __future__ import annotations

from typing import Any

from flask import current_app

from core.hooks import stage_params
from pipeline.stages.spec import StageDeclaration, StageSpec, declared_stages


def runnable_stages() -> tuple[str, ...]:
    """The stages ``keystone run --stages`` accepts, in flow order (judge, crop and review are
    people's work and declare no stage)."""
    return tuple(name for name, declaration in declared_stages().items() if declaration.keystone_run != "never")


def default_run_stages() -> tuple[str, ...]:
    """The stages ``keystone run`` runs when ``--stages`` is not given, in flow order."""
    return tuple(name for name, declaration in declared_stages().items() if declaration.keystone_run == "default")


def stage_parameters(declaration: StageDeclaration[Any]) -> Any:
    """The parameters a run uses for a stage (needs an app context): a feature's, else the
    declaration's defaults, with the declared config fields set from the app's config."""
    params = stage_params(declaration.name, declaration.params)
    return declaration.configured(params, current_app.config)


def available_stages() -> dict[str, StageSpec]:
    """Every declared stage in flow order, ready to run. Needs an app context: the grade
    thresholds come from the newest fitted grade model in the database (or the defaults)."""
    return {name: declaration.spec(stage_parameters(declaration)) for name, declaration in declared_stages().items()}
