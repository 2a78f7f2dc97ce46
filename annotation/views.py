"""Crowd pages and their small JSON API, on the blueprint of :mod:`annotation.blueprint` (the
confirm grid's routes are :mod:`annotation.grid_views`, the curators' :mod:`annotation.staff_views`).

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

from pathlib import Path
from typing import Any

from flask import (
    abort,
    current_app,
    jsonify,
    redirect,
    render_template,
    request,
    url_for,
)
from flask_login import current_user
from werkzeug.wrappers import Response

from core.auth import role_required
from core.db import db, read_only
from core.extensions import csrf
from core.json_body import load_json_body
from core.models import Card
from core.security import frameable_by

from . import questions as question_table
from .answers import submit, undo_last
from .batches import preview_card
from .blueprint import bp
from .crowd_settings import DEFAULT_MIN_BOX_PX, DEFAULT_RESERVATION_MINUTES
from .models import TASK_KINDS, Worker
from .pictures import (
    EXAMPLES,
    EYE_ORDERS,
    example_picture,
    eye_order_picture,
    sample_card_picture,
)
from .progress import answer_count, batch_positions
from .proposals import proposed_boxes, proposed_crop_boxes
from .providers import (
    MTURK_SUBMIT_ORIGINS,
    PROVIDERS,
    Entry,
    SignedWorker,
    load_signed_worker,
    sign_entry,
)
from .reservations import any_unfinished_batch, next_tasks, open_kinds, renew_reservation, reservation_by_token
from .sessions import complete_session
from .task_errors import TaskError
from .workers import account_worker

TOKEN_HEADER = "X-Crowd-Token"
# Curators' pages (annotation.staff_views): their errors render in the staff layout.
STAFF_ENDPOINTS = frozenset(
    {
        "crowd.batches",
        "crowd.new_batch",
        "crowd.rename_batch",
        "crowd.batch_state",
        "crowd.new_invite",
        "crowd.revoke_invite_link",
        "crowd.flag_worker",
        "crowd.check_submissions",
        "crowd.answers_csv",
    }
)


@bp.errorhandler(TaskError)
def task_error(error: TaskError) -> Any:
    db.session.rollback()
    headers = {"Retry-After": str(error.retry_after)} if error.retry_after is not None else {}
    if request.path.startswith("/crowd/api/") or request.accept_mimetypes.best == "application/json":
        return jsonify({"error": {"code": error.status, "message": error.message}}), error.status, headers
    if request.endpoint in STAFF_ENDPOINTS:
        return render_template("annotation/staff_message.html", message=error.message), error.status, headers
    return (
        render_template("annotation/message.html", title="Cannot open this task", message=error.message),
        error.status,
        headers,
    )


def _answered(worker: Worker | int, session: int) -> int:
    # After a use case committed, this read must not take SQLite's write lock again.
    with read_only():
        return answer_count(worker, session)


def _finished_words(entry: Entry) -> tuple[str, str]:
    """The finished screen's title and sentence when nothing is open for this worker now."""
    if entry.worker is not None and (entry.worker.flagged or (entry.session is not None and entry.session.flagged)):
        return "Thank you", "Thank you for your work; there are no more tasks for you."
    minutes = int(float(current_app.config.get("KEYSTONE_CROWD_RESERVATION_MINUTES", DEFAULT_RESERVATION_MINUTES)))
    if any_unfinished_batch():
        return (
            "Nothing for you right now",
            (
                f"Other people hold the remaining cards. Come back in about {minutes} minutes with this same link: "
                "cards they do not finish come back to you."
            ),
        )
    return (
        "All done, thank you!",
        ("You have answered every card open to you. New cards may open later: keep this link, it brings you back to your place."),
    )


def _task_page(entry: Entry) -> str:
    """One link serves whatever is open for this worker: judge first, then crop (``?kind=`` forces one).

    Which kinds have work is a read (nothing is reserved here: the page's first fetch does it).
    With nothing open, the page is the finished screen: the same template without controls, so
    the link keeps working when work opens later.
    """
    forced = request.args.get("kind")
    if forced is not None and forced not in TASK_KINDS:
        raise TaskError(f"Expected kind {', '.join(TASK_KINDS)}, got {forced[:20]!r}")
    worker_token = sign_entry(entry) if entry.worker is not None else ""
    kinds: list[str] = []
    if entry.worker is not None and entry.session is not None:
        with read_only():
            kinds = open_kinds(entry.worker, entry.session.id)
    kind = forced or (kinds[0] if kinds else "judge")
    later = [k for k in kinds if TASK_KINDS.index(k) > TASK_KINDS.index(kind)]
    finished = entry.worker is not None and not forced and not kinds
    title, message = _finished_words(entry) if finished else ("", "")
    answered = _answered(entry.worker, entry.session.id) if entry.worker is not None and entry.session else 0
    here = url_for(
        request.endpoint or "crowd.invite", **(request.view_args or {}), **{k: v for k, v in request.args.items() if k != "kind"}
    )
    page = "grid" if kind == "confirm" else "judge"
    return render_template(
        f"annotation/{kind}.html",
        entry=entry,
        worker_token=worker_token,
        answered=answered,
        min_box=current_app.config.get("KEYSTONE_CROWD_MIN_BOX_PX", DEFAULT_MIN_BOX_PX),
        finished=finished,
        finished_title=title,
        finished_message=message,
        next_kind_url=(here + ("&" if "?" in here else "?") + f"kind={later[0]}") if later else "",
        entry_url=here,
        examples=EXAMPLES,
        # The page's questions: drawn by annotation/_questions.html, and as JSON for its script.
        questions=question_table.grid_questions() if page == "grid" else question_table.judge_questions(),
        question_table=question_table.page_table(page),
    )


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


@bp.route("/mine")
@role_required("annotator")
def mine() -> Response:
    """A logged-in annotator's own link: their account's invited worker, made on first use."""
    worker = account_worker(current_user.id, current_user.username)
    return redirect(url_for("crowd.invite", token=worker.token), code=303)


@bp.route("/preview.jpg")
@frameable_by("'self'", *MTURK_SUBMIT_ORIGINS)
def preview_image() -> Response:
    """What an MTurk preview shows: a card of the oldest open judge batch, else the synthetic example card."""
    from catalogue.views import ensure_previews, preview_etag
    from core.http_images import send_image as _send_image

    with read_only():
        card = preview_card()
        found = (card.content_hash, card.stored_path) if card is not None else None
    if found is None:
        response = Response(sample_card_picture(), mimetype="image/jpeg")
    else:
        response = _send_image(ensure_previews(*found)["display"], "image/jpeg", preview_etag(found[0], "display"))
    response.headers["Cache-Control"] = "public, max-age=600"
    return response


@bp.route("/examples/<name>.jpg")
def example(name: str) -> Response:
    """An instruction picture (a good crop, a bad crop, an upside-down card, a negative), made once per process."""
    if name not in EXAMPLES:
        abort(404, "No such example picture.")
    response = Response(example_picture(name), mimetype="image/jpeg")
    response.headers["Cache-Control"] = "public, max-age=86400"
    return response


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
    # Bounded in size, depth and numbers: a 415 or 400 with the reason (core.json_body).
    return caller, load_json_body()


def _task_json(task: Any) -> dict[str, Any]:
    document = {**task.as_json(), "image_url": url_for("crowd.task_image", token=task.reservation_token)}
    if task.kind == "judge":
        # The key keeps its old name: it is the task JSON's contract (docs/CROWD.md), now still pictures.
        document["wiggle_urls"] = {
            order: url_for("crowd.task_eye_order", token=task.reservation_token, order=order) for order in EYE_ORDERS
        }
    elif task.kind == "crop":
        with read_only():
            card = db.session.get(Card, task.card_id)
            proposal = proposed_crop_boxes(card) if card is not None else None
        document["proposed"] = proposal.as_json() if proposal is not None else None
    return document


def _positions(worker_id: int, tasks: list[Any]) -> dict[str, dict[str, int]]:
    with read_only():
        return {str(b): p for b, p in batch_positions(worker_id, {t.batch_id for t in tasks}).items()}


@csrf.exempt
@bp.route("/api/next", methods=["POST"])
def api_next() -> Any:
    caller, body = _api_entry()
    kind = body.get("kind", "judge")
    if kind == "confirm":
        raise TaskError("Confirm tasks come as a grid: fetch them from /crowd/api/grid")
    if kind not in TASK_KINDS:
        raise TaskError(f"Expected kind judge or crop, got {kind!r}")
    tasks, why = next_tasks(caller.worker_id, kind, session=caller.session_id)
    return jsonify(
        {
            "tasks": [_task_json(t) for t in tasks],
            "answered": caller.answered,
            "positions": _positions(caller.worker_id, tasks),
            "reason": why.reason.value if why else None,
            "retry_after": why.retry_after.isoformat() if why and why.retry_after else None,
        }
    )


@csrf.exempt
@bp.route("/api/submit", methods=["POST"])
def api_submit() -> Any:
    caller, body = _api_entry()
    result = submit(caller.worker_id, body.get("token"), body.get("answer"), body.get("key"), session=caller.session_id)
    document = {"answer": result.answer_id, "duplicate": result.duplicate, "answered": caller.answered + (not result.duplicate)}
    if caller.provider == "mturk":
        document["finish"] = PROVIDERS["mturk"].finish(caller.context)
    return jsonify(document), 200 if result.duplicate else 201


@csrf.exempt
@bp.route("/api/renew", methods=["POST"])
def api_renew() -> Any:
    """Keep a task the annotator is still working on: extend its reservation (also once it lapsed)."""
    caller, body = _api_entry()
    task = renew_reservation(caller.worker_id, body.get("token"), session=caller.session_id)
    return jsonify({"task": _task_json(task)})


@csrf.exempt
@bp.route("/api/undo", methods=["POST"])
def api_undo() -> Any:
    caller, _ = _api_entry()
    undone = undo_last(caller.worker_id, session=caller.session_id)
    # The withdrawn answer comes back with its task: the page shows it again, so a quick Enter
    # resends what was said rather than a blank card.
    return jsonify({"task": _task_json(undone.task), "answer": undone.answer, "answered": caller.answered - 1})


@bp.route("/finish")
def finish() -> Response:
    """The end of a session: Prolific's completion redirect (the token comes in the link).

    The token names one session, so this completes that session only; when it was completed
    is recorded on it (what a researcher checks before approving a submission).
    """
    with read_only():
        caller = load_signed_worker(request.args.get("t"), finished_ok=True)
    try:
        outcome = PROVIDERS[caller.provider].finish(caller.context)
    except TaskError:
        # Prolific with no completion code configured: the answers are saved and the session is
        # complete; say so, and what to tell the researcher, rather than fail the participant.
        outcome = {
            "message": "Your answers are saved and your session is recorded as complete. This study "
            "has no completion code set up here, so you cannot be sent back to Prolific "
            "automatically: return to Prolific and message the researcher, quoting your "
            f"session {caller.context.get('session', '')}."
        }
    complete_session(caller.session_id)
    if "redirect" not in outcome:
        return Response(
            render_template(
                "annotation/message.html",
                title="Thank you",
                message=outcome.get("message", "Your answers are saved. You can close this page."),
            )
        )
    return redirect(outcome["redirect"], code=303)


@bp.route("/task/<token>/image")
def task_image(token: str) -> Response:
    """The display image of a reserved card, named by the reservation token (never a card id or path)."""
    from catalogue.views import ensure_previews, preview_etag
    from core.http_images import not_modified as _not_modified, send_image as _send_image

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


@bp.route("/task/<token>/eye-order/<order>.jpg")
def task_eye_order(token: str, order: str) -> Response:
    """The eye-order picture of a reserved card (its depth in colour, near warm, far cool): its photos
    as scanned (``as-is``) or exchanged (``swapped``)."""
    from pipeline.errors import PipelineError
    from pipeline.io import read_image

    if order not in EYE_ORDERS:
        abort(404, "No such eye order.")
    with read_only():
        reservation = reservation_by_token(token)
        if reservation is None:
            abort(404, "No such task.")
        card = reservation.item.card
        proposal = proposed_boxes(card)
        key, width, height = (card.id, card.content_hash), card.width, card.height
        path = Path(current_app.config["KEYSTONE_DATA_DIR"]).resolve() / card.stored_path
    left, right = (
        (proposal.left, proposal.right)
        if proposal is not None
        else ([0, 0, width // 2, height], [width - width // 2, 0, width, height])
    )
    try:
        data = eye_order_picture(key, lambda: read_image(path), left, right, order)
    except (OSError, ValueError, PipelineError) as exc:  # a missing or unreadable original, photo boxes too small
        abort(404, f"No eye-order picture for this card: {exc}")
    response = Response(data, mimetype="image/jpeg")
    response.headers["Cache-Control"] = "private, max-age=3600"
    return response
