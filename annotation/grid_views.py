"""The confirm grid's routes: fetch a grid, submit its taps, each card's picture, the curators' door.

The page itself is the crowd entry page (``annotation.views._task_page`` renders
``annotation/confirm.html`` when confirm work is open or ``?kind=confirm`` asks for it); its
API calls carry the signed worker token like the judge and crop pages (see
:mod:`annotation.views` for why no cookies).
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from flask import abort, jsonify, redirect, url_for
from flask_login import current_user
from werkzeug.wrappers import Response

from core.auth import role_required
from core.db import read_only
from core.extensions import csrf

from .blueprint import bp
from .grid_pictures import grid_picture, picture_key
from .grids import card_photo_boxes, next_grid, submit_grid
from .providers import PROVIDERS
from .reservations import Task, reservation_by_token
from .views import _api_entry
from .workers import account_worker


def _grid_card(task: Task) -> dict[str, Any]:
    # Nothing here tells a gold card from a regular one: same batch, same kind of token and URL.
    return {
        "token": task.reservation_token,
        "picture_url": url_for("crowd.grid_image", token=task.reservation_token),
        "expires_at": task.expires_at.isoformat(),
    }


@csrf.exempt
@bp.route("/api/grid", methods=["POST"])
def api_grid() -> Any:
    """The worker's grid (the one their session holds, else a new one), or why there is none."""
    caller, _ = _api_entry()
    tasks, why = next_grid(caller.worker_id, session=caller.session_id)
    return jsonify(
        {
            "cards": [_grid_card(t) for t in tasks],
            "answered": caller.answered,
            "reason": why.reason.value if why else None,
            "retry_after": why.retry_after.isoformat() if why and why.retry_after else None,
        }
    )


@csrf.exempt
@bp.route("/api/grid/submit", methods=["POST"])
def api_grid_submit() -> Any:
    """``{"key": ..., "answers": [{"token", "taps": {"upside_down", "inverted", "swapped"}}]}``:
    201 when something was stored, 200 when all of it had been (a repeated post)."""
    caller, body = _api_entry()
    result = submit_grid(caller.worker_id, body.get("answers"), body.get("key"), session=caller.session_id)
    document = {**result.as_json(), "answered": caller.answered + result.stored}
    if caller.provider == "mturk":
        document["finish"] = PROVIDERS["mturk"].finish(caller.context)
    return jsonify(document), 201 if result.stored else 200


@bp.route("/task/<token>/grid.jpg")
def grid_image(token: str) -> Response:
    """One grid card's picture (:mod:`annotation.grid_pictures`), named by its reservation token."""
    from catalogue.views import ensure_previews
    from core.http_images import not_modified, send_image

    with read_only():
        reservation = reservation_by_token(token)
        if reservation is None or reservation.item.batch.kind != "confirm":
            abort(404, "No such grid card.")
        card, shown = reservation.item.card, reservation.item.shown or {}
        left, right = card_photo_boxes(card)
        content_hash, stored_path, width = card.content_hash, card.stored_path, card.width
    key = picture_key(content_hash, left, right, shown)
    cached = not_modified(key)
    if cached is not None:
        return cached

    def load() -> np.ndarray:
        from PIL import Image

        display = ensure_previews(content_hash, stored_path)["display"]
        with Image.open(io.BytesIO(display) if isinstance(display, bytes) else display) as image:
            return np.asarray(image.convert("RGB"))

    try:
        data = grid_picture(key, load, width, left, right, shown)
    except ValueError as exc:  # boxes that cut no photo out of this card
        abort(404, f"No picture for this card: {exc}")
    return send_image(data, "image/jpeg", key)


@bp.route("/grid")
@role_required("annotator", "curator")
def staff_grid() -> Response:
    """Curators and in-house annotators confirm cards too: their account's worker, on the grid page."""
    worker = account_worker(current_user.id, current_user.username)
    return redirect(url_for("crowd.invite", token=worker.token, kind="confirm"), code=303)
