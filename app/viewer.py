"""The view-synthesis viewer page (filled in by the view-synthesis feature)."""

from __future__ import annotations

from flask import Blueprint

bp = Blueprint("viewer", __name__, url_prefix="/viewer")
