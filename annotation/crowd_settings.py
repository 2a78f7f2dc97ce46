"""The crowd's settings: the app's ``KEYSTONE_CROWD_*`` config values, with their defaults.

Read inside an app context, at each use (tests and the benchmark change them per app).
"""

from __future__ import annotations

from datetime import timedelta

from flask import current_app

DEFAULT_RESERVATION_MINUTES = 10
DEFAULT_MIN_BOX_PX = 16
DEFAULT_GOLD_THRESHOLD = 0.7
DEFAULT_MIN_GOLD = 3
DEFAULT_GRID_SIZE = 30  # cards a confirm grid shows, gold included (24 to 48 fit a screen or two)
DEFAULT_GRID_GOLD = 3  # gold cards hidden in each grid
MAX_GRID = 48
# How long a task page's signed worker token is good for (a working day of one open tab); then
# the page must be opened again from the worker's link, which signs a fresh one.
DEFAULT_TOKEN_HOURS = 8.0


def reservation_ttl() -> timedelta:
    """How long a fetched task stays reserved for its worker."""
    minutes = current_app.config.get("KEYSTONE_CROWD_RESERVATION_MINUTES", DEFAULT_RESERVATION_MINUTES)
    return timedelta(minutes=float(minutes))


def min_box_px() -> int:
    """The smallest width and height, in original pixels, of a crop box an answer may give."""
    return int(current_app.config.get("KEYSTONE_CROWD_MIN_BOX_PX", DEFAULT_MIN_BOX_PX))


def gold_threshold() -> float:
    """The gold accuracy below which a worker is flagged."""
    return float(current_app.config.get("KEYSTONE_CROWD_GOLD_THRESHOLD", DEFAULT_GOLD_THRESHOLD))


def min_gold() -> int:
    """How many gold answers a worker gives before their accuracy can flag them."""
    return int(current_app.config.get("KEYSTONE_CROWD_MIN_GOLD", DEFAULT_MIN_GOLD))


def grid_size() -> tuple[int, int]:
    """(cards per confirm grid, gold cards among them): ``KEYSTONE_CROWD_GRID_SIZE`` and
    ``KEYSTONE_CROWD_GRID_GOLD``, at most :data:`MAX_GRID` cards and always one regular card."""
    size = int(current_app.config.get("KEYSTONE_CROWD_GRID_SIZE", DEFAULT_GRID_SIZE))
    gold = int(current_app.config.get("KEYSTONE_CROWD_GRID_GOLD", DEFAULT_GRID_GOLD))
    size = max(1, min(size, MAX_GRID))
    return size, max(0, min(gold, size - 1))


def token_lifetime_s() -> float:
    """Seconds a signed worker token is accepted after it was signed (``KEYSTONE_CROWD_TOKEN_HOURS``)."""
    hours = float(current_app.config.get("KEYSTONE_CROWD_TOKEN_HOURS", DEFAULT_TOKEN_HOURS))
    if not hours > 0:
        raise ValueError(f"Expected KEYSTONE_CROWD_TOKEN_HOURS > 0, got {hours}")
    return hours * 3600.0
