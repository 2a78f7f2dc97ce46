"""The view-synthesis viewer: a card's five GD images as textured meshes in WebGL (the real-time viewer of KeystoneDepth, Luo et al.).

The page reads the card's latest ``views`` stage result (:mod:`pipeline.view_synthesis`): its scene
document (``views.json``: the five cameras and the mesh grid) goes into the page, and
``app/static/viewer.js`` fetches, per view, the picture as a JPEG (``v<i>_web``: colour where the
card has it) and its depth as quantised inverse depth on the mesh grid (``v<i>_mesh``, a small PNG)
through :func:`view_file`, builds one grid mesh per view (triangles dropped only at depth edges), and
blends them by the virtual camera's distance to each of v0..v4. About 0.3-0.5 MB a card; the PNGs
and float32 ``.npy`` maps stay for releases and are served too, but the page does not fetch them.

Files are served by card id and an artifact name from a fixed list, never from a path a request
controls, with an ETag; a URL carrying the current ``?v=`` version is cacheable for a year, any
other must revalidate (a rerun of the stage changes the version).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from flask import Blueprint, abort, render_template, request, url_for
from werkzeug.wrappers import Response

from catalogue.views import get_card_or_404, inside_data_dir
from core.auth import role_required
from core.db import read_only
from core.models import ROLES, Card, StageResult

bp = Blueprint("viewer", __name__, url_prefix="/viewer", template_folder="templates")

VIEW_NAMES: tuple[str, ...] = ("v0", "v1", "v2", "v3", "v4")
# Artifact name -> mimetype: the only files this blueprint serves.
VIEW_FILES: dict[str, str] = {
    **{name: "image/png" for name in VIEW_NAMES},
    **{f"{name}_web": "image/jpeg" for name in VIEW_NAMES},
    **{f"{name}_mesh": "image/png" for name in VIEW_NAMES},
    **{f"{name}_depth": "application/octet-stream" for name in VIEW_NAMES},
    "preview": "image/webp",
    "scene": "application/json",
}
CACHE_FOREVER = "private, max-age=31536000, immutable"
CACHE_REVALIDATE = "private, no-cache"


def get_views_or_404(card: Card) -> StageResult:
    """The card's latest ``views`` result when it is done, else 404 saying why there are no views."""
    result = card.latest_results().get("views")
    if result is None:
        abort(404, f"Card {card.id} has no 3D views yet: the views stage has not run on it.")
    if result.status != "done":
        abort(404, f"Card {card.id} has no views: {result.status}, {result.reason or 'no reason recorded'}.")
    return result


def view_etag(card: Card, result: StageResult, name: str) -> str:
    detail = f"views\0{name}\0{(result.artifacts or {}).get(name)}\0{result.id}\0{result.code_version}"
    return f"{card.content_hash}-{result.param_hash}-{hashlib.sha256(detail.encode()).hexdigest()[:12]}"


def _version(etag: str) -> str:
    return hashlib.sha256(etag.encode()).hexdigest()[:16]


def view_file_url(card: Card, result: StageResult, name: str) -> str:
    return url_for("viewer.view_file", card_id=card.id, name=name, v=_version(view_etag(card, result, name)))


@bp.route("/cards/<int:card_id>")
@role_required(*ROLES)
def card_view(card_id: int) -> Any:
    with read_only():
        card = get_card_or_404(card_id)
        result = get_views_or_404(card)
        relative = (result.artifacts or {}).get("scene")
        if not isinstance(relative, str):
            abort(404, f"The views of card {card_id} have no scene document; rerun the views stage.")
        path = inside_data_dir(relative)
        if not path.is_file():
            abort(404, "The views are recorded but their files are missing; rerun the views stage.")
        scene = json.loads(path.read_text())
        files = {name: view_file_url(card, result, name) for name in VIEW_FILES if name in (result.artifacts or {})}
        missing = [name for name in (*(f"{n}_web" for n in VIEW_NAMES), *(f"{n}_mesh" for n in VIEW_NAMES)) if name not in files]
        if missing or not isinstance(scene.get("mesh"), dict):
            abort(
                404,
                f"The views of card {card_id} were made before the viewer's compact files "
                f"({', '.join(missing) or 'mesh grid'} missing); rerun `keystone run --stages views`.",
            )
        config = {
            "width": scene["width"],
            "height": scene["height"],
            "sceneCentre": scene["scene_centre"],
            "quadRadius": scene["quad_radius"],
            "depthRange": scene["depth_range"],
            "maxRelativeStep": scene.get("max_relative_step", 0.1),
            "maxStretchPx": scene.get("max_stretch_px"),
            "colour": bool(scene.get("colour")),
            "mesh": {
                "step": scene["mesh"]["step"],
                "columns": scene["mesh"]["columns"],
                "rows": scene["mesh"]["rows"],
                "inverseDepthRange": scene["mesh"]["inverse_depth_range"],
            },
            "views": [
                {
                    "name": view["name"],
                    "rotation": view["rotation"],
                    "translation": view["translation"],
                    "centre": view["centre"],
                    "focal": view["focal_px"],
                    "image": files[f"{view['name']}_web"],
                    "mesh": files[f"{view['name']}_mesh"],
                }
                for view in scene["views"]
            ],
        }
        return render_template(
            "viewer/card.html",
            card=card,
            result=result,
            config=config,
            preview_url=files.get("preview"),
            metrics=result.metrics or {},
        )


@bp.route("/cards/<int:card_id>/files/<name>")
@role_required(*ROLES)
def view_file(card_id: int, name: str) -> Response:
    """One file of the card's latest views: ``v0``..``v4`` (PNG), ``v0_depth``..``v4_depth``
    (float32 .npy), ``v0_web``..``v4_web`` (JPEG), ``v0_mesh``..``v4_mesh`` (the viewer's depth PNG),
    ``preview`` (animated WebP) or ``scene`` (JSON)."""
    if name not in VIEW_FILES:
        abort(404, f"There is no view file called {name!r}; expected one of {', '.join(VIEW_FILES)}.")
    with read_only():
        card = get_card_or_404(card_id)
        result = get_views_or_404(card)
        relative = (result.artifacts or {}).get(name)
        if not isinstance(relative, str) or not relative:
            abort(404, f"The views of card {card_id} have no {name!r}.")
        etag = view_etag(card, result, name)
    path = inside_data_dir(relative)
    if request.if_none_match.contains(etag):
        response = Response(status=304)
    else:
        if not path.is_file():
            abort(404, f"View file {name!r} is recorded but missing; rerun the views stage.")
        response = Response(Path(path).read_bytes(), mimetype=VIEW_FILES[name])
        response.last_modified = path.stat().st_mtime
    response.set_etag(etag)
    pinned = request.args.get("v") == _version(etag)
    response.headers["Cache-Control"] = CACHE_FOREVER if pinned else CACHE_REVALIDATE
    return response
