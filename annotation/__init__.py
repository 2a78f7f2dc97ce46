"""Crowd annotation: judge and crop tasks, assignment, providers, aggregation, worker quality.

The pure core (``assignment``, ``aggregation``, ``agreement``) imports neither Flask nor
SQLAlchemy; ``models``, ``tasks``, ``providers``, ``views`` and ``cli`` are the shell around it.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    # Lazy, so importing the pure modules (annotation.assignment, ...) never pulls in Flask.
    if name == "bp":
        # Each module adds its routes to the one blueprint (annotation.blueprint) when imported.
        from . import grid_views, staff_views, views  # noqa: F401
        from .blueprint import bp

        return bp
    raise AttributeError(name)
