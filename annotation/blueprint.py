"""The crowd's blueprint (``/crowd``), which the task pages (:mod:`annotation.views`), the confirm
grid (:mod:`annotation.grid_views`) and the curators' pages (:mod:`annotation.staff_views`) each
add their routes to. It lives apart so that none of them imports another for it (no cycle);
``annotation.bp`` imports all three, which registers their routes.
"""

from __future__ import annotations

from flask import Blueprint

from core.auth import add_nav_link

from . import run_hooks

bp = Blueprint("crowd", __name__, url_prefix="/crowd", template_folder="templates", static_folder="static")
bp.record_once(lambda state: add_nav_link(state.app, "Crowd", "crowd.batches", "curator", order=40))
bp.record_once(lambda state: run_hooks.register(state.app))
bp.record_once(lambda state: add_nav_link(state.app, "My tasks", "crowd.mine", "annotator", order=35, home_of=("annotator",)))
