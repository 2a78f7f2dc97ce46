"""``keystone report`` and ``keystone grade ...``."""

from __future__ import annotations

import click


def commands() -> list[click.Command]:
    """Top-level commands this feature adds to ``keystone``."""
    return []
