"""``keystone export``, ``keystone verify`` and ``keystone bench export``."""

from __future__ import annotations

import click


def commands() -> list[click.Command]:
    """Top-level commands this feature adds to ``keystone``."""
    return []


def bench_commands() -> list[click.Command]:
    """Commands this feature adds to ``keystone bench``."""
    return []
