"""Crowd pages and their small JSON API.

Identity and anti-forgery: crowd routes do not use the session cookie. MTurk shows the page
in an iframe on mturk.com, where browsers block third-party cookies, so a cookie-based login
or CSRF token would silently fail there. The entry page instead embeds a token signed with
the app's secret key (worker id, session id and provider context; :mod:`annotation.sessions`
says why the API trusts a session and not a participant id). The page's script sends it in
the ``X-Crowd-Token`` header on every API call, with a JSON body. That header doubles as the
anti-forgery token: another site cannot read it, an HTML form cannot set a header, and a
cross-origin ``fetch`` with a custom header or a JSON content type needs a CORS preflight
that this app never grants. So the API routes are exempt from the cookie-based CSRFProtect
and refuse any POST without a valid token (403) or without a JSON body (415/400).
"""

from __future__ import annotations

from typing import Any

from flask import (
    Blueprint,
    abort,
    current_app,
    jsonify,
    redirect,
    render_template,
    request,
    url_for,
)
from sqlalchemy import select
from werkzeug.wrappers import Response

from app.auth import add_nav_link, role_required
from app.db import db, read_only
from app.extensions import csrf
from app.json_body import load_json_body
from app.security import frameable_by

from . import run_hooks
from .models import TASK_KINDS, Batch, Worker
from .providers import (
    MTURK_SUBMIT_ORIGINS,
    PROVIDERS,
    Entry,
    SignedWorker,
    load_signed_worker,
    sign_entry,
)
from .sessions import complete_session
from .tasks import (
    DEFAULT_MIN_BOX_PX,
    TaskError,
    answer_count,
    batch_progress,
    next_tasks,
    reservation_by_token,
    submit,
    undo_last,
    worker_progress,
)

bp = Blueprint("crowd", __name__, url_prefix="/crowd", template_folder="templates", static_folder="static")
bp.record_once(lambda state: add_nav_link(state.app, "Crowd", "crowd.batches", "curator", order=40))
bp.record_once(lambda state: run_hooks.register(state.app))

TOKEN_HEADER = "X-Crowd-Token"


@bp.errorhandler(TaskError)
def task_error(error: TaskError) -> Any:
    db.session.rollback()
    headers = {"Retry-After": str(error.retry_after)} if error.retry_after is not None else {}
    if request.path.startswith("/crowd/api/") or request.accept_mimetypes.best == "application/json":
        return jsonify({"error": {"code": error.status, "message": error.message}}), error.status, headers
    return (render_template("annotation/message.html", title="Cannot open this task", message=error.message),
            error.status, headers)


def _answered(worker: Worker | int, session: int) -> int:
    # After a use case committed, this read must not take SQLite's write lock again.
    with read_only():
        return answer_count(worker, session)


def _task_page(entry: Entry) -> str:
    """The judge page, or the crop page with ``?kind=crop`` on any entry link."""
    kind = request.args.get("kind", "judge")
    if kind not in TASK_KINDS:
        raise TaskError(f"Expected kind judge or crop, got {kind!r}")
    worker_token = sign_entry(entry) if entry.worker is not None else ""
    answered = _answered(entry.worker, entry.session.id) if entry.worker is not None and entry.session else 0
    return render_template(f"annotation/{kind}.html", entry=entry, worker_token=worker_token, answered=answered,
                           min_box=current_app.config.get("KEYSTONE_CROWD_MIN_BOX_PX", DEFAULT_MIN_BOX_PX))


@bp.route("/invite/<token>")
def invite(token: str) -> str:
    return _task_page(PROVIDERS["invite"].enter({"token": token}))


@bp.route("/prolific")
def prolific() -> str:
    return _task_page(PROVIDERS["prolific"].enter(request.args.to_dict()))


@bp.route("/mturk")
@frameable_by("'self'", *MTURK_SUBMIT_ORIGINS)
def mturk() -> str:
    return _task_page(PROVIDERS["mturk"].enter(request.args.to_dict()))


# ---------------------------------------------------------------------------------------------
# JSON API (token in the X-Crowd-Token header; see the module docstring)


def _api_entry() -> tuple[SignedWorker, dict[str, Any]]:
    """The worker (from the signed token, with their progress so far) and the JSON body.

    Only reads, in a deferred transaction: under SQLite's BEGIN IMMEDIATE they would queue every
    API call behind the writers. The progress is read here, before the use case, to save a
    transaction per call (two tabs of one worker may see it one behind for a moment).
    """
    with read_only():
        caller = load_signed_worker(request.headers.get(TOKEN_HEADER))
    # Bounded in size, depth and numbers: a 415 or 400 with the reason (app.json_body).
    return caller, load_json_body()


def _task_json(task: Any) -> dict[str, Any]:
    return {**task.as_json(), "image_url": url_for("crowd.task_image", token=task.reservation_token)}


@csrf.exempt
@bp.route("/api/next", methods=["POST"])
def api_next() -> Any:
    caller, body = _api_entry()
    kind = body.get("kind", "judge")
    if kind not in TASK_KINDS:
        raise TaskError(f"Expected kind judge or crop, got {kind!r}")
    tasks, why = next_tasks(caller.worker_id, kind, session=caller.session_id)
    return jsonify({"tasks": [_task_json(t) for t in tasks], "answered": caller.answered,
                    "reason": why.reason.value if why else None,
                    "retry_after": why.retry_after.isoformat() if why and why.retry_after else None})


@csrf.exempt
@bp.route("/api/submit", methods=["POST"])
def api_submit() -> Any:
    caller, body = _api_entry()
    result = submit(caller.worker_id, body.get("token"), body.get("answer"), body.get("key"), session=caller.session_id)
    document = {"answer": result.answer_id, "duplicate": result.duplicate,
                "answered": caller.answered + (not result.duplicate)}
    if caller.provider == "mturk":
        document["finish"] = PROVIDERS["mturk"].finish(caller.context)
    return jsonify(document), 200 if result.duplicate else 201


@csrf.exempt
@bp.route("/api/undo", methods=["POST"])
def api_undo() -> Any:
    caller, _ = _api_entry()
    task = undo_last(caller.worker_id, session=caller.session_id)
    return jsonify({"task": _task_json(task), "answered": caller.answered - 1})


@bp.route("/finish")
def finish() -> Response:
    """The end of a session: Prolific's completion redirect (the token comes in the link).

    The token names one session, so this completes that session only; when it was completed
    is recorded on it (what a researcher checks before approving a submission).
    """
    with read_only():
        caller = load_signed_worker(request.args.get("t"))
    outcome = PROVIDERS[caller.provider].finish(caller.context)
    complete_session(caller.session_id)
    if "redirect" not in outcome:
        return Response(render_template("annotation/message.html", title="Thank you",
                                        message="Your answers are saved. You can close this page."))
    return redirect(outcome["redirect"], code=303)


@bp.route("/task/<token>/image")
def task_image(token: str) -> Response:
    """The display image of a reserved card, named by the reservation token (never a card id or path)."""
    from app.catalog import _not_modified, _send_image, ensure_previews, preview_etag

    with read_only():
        reservation = reservation_by_token(token)
        if reservation is None:
            abort(404, "No such task image.")
        card = reservation.item.card
        content_hash, stored_path = card.content_hash, card.stored_path
    etag = preview_etag(content_hash, "display")
    cached = _not_modified(etag)
    if cached is not None:
        return cached
    response = _send_image(ensure_previews(content_hash, stored_path)["display"], "image/jpeg", etag)
    response.headers["Cache-Control"] = "private, max-age=3600"
    return response


# ---------------------------------------------------------------------------------------------
# Staff


@bp.route("/batches")
@role_required("curator")
def batches() -> str:
    with read_only():
        rows = [batch_progress(b) for b in db.session.scalars(select(Batch).order_by(Batch.id.desc()))]
        workers = {w.id: w for w in db.session.scalars(select(Worker))}
        return render_template("annotation/batches.html", batches=rows, workers=workers, crowd=worker_progress(),
                               configured=bool(current_app.config.get("KEYSTONE_PROLIFIC_COMPLETION_CODE")))
