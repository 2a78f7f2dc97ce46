"""Release pages (filled in by the releases feature)."""

from __future__ import annotations

from flask import Blueprint

bp = Blueprint("exports", __name__, url_prefix="/releases", template_folder="templates")
