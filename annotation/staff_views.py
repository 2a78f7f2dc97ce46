"""Crowd management for curators: batches, invite links, progress per batch and worker, flagging,
Prolific submissions, answer exports.

Every POST is a form with the cookie session's CSRF token (CSRFProtect), runs one crowd use case
(:mod:`annotation.batches`, :mod:`annotation.workers`, ...) and redirects back with a flash message saying what happened (or why
nothing did: a TaskError's sentence, 4xx when the request itself was bad).
"""

from __future__ import annotations

import io
import re
import secrets
from typing import Any

from flask import abort, current_app, flash, redirect, render_template, request, url_for
from flask_login import current_user
from sqlalchemy import func, select
from werkzeug.wrappers import Response

from core.auth import role_required
from core.db import db, read_only
from core.limits import parse_positive_int, parse_whole_number
from core.spreadsheet_csv import write_spreadsheet_csv

from .batches import AlreadyCreated, confirm_gold, confirm_queue_card_ids, create_batch, review_queue_card_ids
from .blueprint import bp
from .cli import ANSWER_COLUMNS, answer_rows
from .models import TASK_KINDS, Batch, CrowdSession, Worker
from .progress import batch_progress, worker_progress
from .providers import InviteProvider
from .task_errors import TaskError
from .workers import check_prolific_submissions, set_worker_flag

MAX_CARD_IDS = 10_000
# The new-batch form's one-time key (a hidden field made with each batches page): what makes a
# repeated submit of the same form land on the batch the first one made.
REQUEST_KEY = re.compile(r"[A-Za-z0-9_-]{16,64}")


def _back() -> Response:
    return redirect(url_for("crowd.batches"), code=303)


def _card_ids(text: str) -> list[int]:
    parts = text.replace(",", " ").split()
    if len(parts) > MAX_CARD_IDS:
        raise TaskError(f"Expected at most {MAX_CARD_IDS} card ids, got {len(parts)}")
    try:
        return [parse_positive_int(p, "a card id") for p in parts]
    except ValueError as exc:
        raise TaskError(f"Card ids are whole numbers separated by commas or spaces. {exc}") from None


def _number(name: str, default: str, kind: type, low: float, high: float) -> Any:
    raw = request.form.get(name, default).strip() or default
    label = name.replace("_", " ")
    if kind is int:
        try:
            return parse_whole_number(raw, label, minimum=int(low), maximum=int(high))
        except ValueError as exc:
            raise TaskError(str(exc)) from None
    # float() also reads "1_0", fullwidth digits, "nan" and "1e999": only plain ASCII decimals here.
    if not (raw.isascii() and len(raw) <= 20 and raw.replace(".", "", 1).isdigit()):
        raise TaskError(f"Expected {label} to be a number like 0.25, got {raw[:20]!r}")
    value = kind(raw)
    if not low <= value <= high:
        raise TaskError(f"Expected {low:g} <= {label} <= {high:g}, got {value}")
    return value


@bp.route("/batches")
@role_required("curator")
def batches() -> str:
    with read_only():
        rows = [batch_progress(b) for b in db.session.scalars(select(Batch).order_by(Batch.id.desc()))]
        workers = {w.id: w for w in db.session.scalars(select(Worker))}
        invited = [
            w for w in workers.values() if w.provider == "invite" and w.person_id is None and not w.external_id.startswith("sim-")
        ]
        review_queue = len(review_queue_card_ids())
        prolific = (
            db.session.scalar(select(func.count()).select_from(CrowdSession).where(CrowdSession.provider == "prolific")) or 0
        )
        return render_template(
            "annotation/batches.html",
            batches=rows,
            workers=workers,
            crowd=worker_progress(),
            invited=sorted(invited, key=lambda w: w.id),
            review_queue=review_queue,
            prolific_sessions=prolific,
            kinds=TASK_KINDS,
            configured=bool(current_app.config.get("KEYSTONE_PROLIFIC_COMPLETION_CODE")),
            submission_checks=None,
            batch_request_key=secrets.token_urlsafe(18),
        )


@bp.route("/batches/new", methods=["POST"])
@role_required("curator")
def new_batch() -> Response:
    kind = request.form.get("kind", "judge")
    if kind not in TASK_KINDS:
        raise TaskError(f"Expected kind {', '.join(TASK_KINDS)}, got {kind[:20]!r}")
    n = _number("answers_per_item", "3", int, 1, 50)
    gold_rate = _number("gold_rate", "0.1", float, 0.0, 1.0)
    gold: dict[int, dict[str, bool]] = {}
    shown: dict[int, dict[str, bool]] = {}
    with read_only():
        ids = _card_ids(request.form.get("cards", ""))
        if request.form.get("from_review"):
            ids += confirm_queue_card_ids() if kind == "confirm" else review_queue_card_ids()
        if kind == "confirm" and ids:
            gold, shown = confirm_gold(exclude=ids)  # every grid hides gold
    if not ids:
        raise TaskError("No cards: tick 'the review queue' (it must not be empty) or list card ids")
    key = request.form.get("request_key") or None
    if key is not None and not REQUEST_KEY.fullmatch(key):
        raise TaskError("This form is out of date: reload the batches page and submit it again")
    try:
        batch = create_batch(ids, kind, n, gold_rate, gold=gold, shown=shown, created_by=current_user.id, request_key=key)
    except AlreadyCreated as done:
        flash(
            f"This form was already submitted: it made batch {done.batch_id}, so no new batch was created. "
            "To make another batch, fill in the form again.",
            "info",
        )
        return redirect(url_for("crowd.batches", _anchor=f"batch-{done.batch_id}"), code=303)
    progress = batch_progress(batch)
    flash(
        f"Batch {batch.id} created: {progress['items']} {kind} cards, {n} answers each "
        f"({progress['answers_needed']} answers needed). Annotators with an invite link get it on their next visit.",
        "success",
    )
    return _back()


@bp.route("/invites", methods=["POST"])
@role_required("curator")
def new_invite() -> Response:
    name = request.form.get("name", "").strip()
    if not name or len(name) > 120 or any(c in name for c in "\r\n\t"):
        raise TaskError("Expected the annotator's name: 1 to 120 characters on one line")
    worker = InviteProvider.invite(name)
    link = url_for("crowd.invite", token=worker.token, _external=True)
    flash(f"Invite link for {name} (send it to them; it is their login): {link}", "success")
    return _back()


@bp.route("/workers/<int:worker_id>/flag", methods=["POST"])
@role_required("curator")
def flag_worker(worker_id: int) -> Response:
    flagged = request.form.get("flagged") == "1"
    worker = set_worker_flag(worker_id, flagged)
    name = f"{worker.provider}:{worker.external_id}"
    flash(
        f"Flagged {name}: their answers leave the results and they get no more cards."
        if flagged
        else f"Cleared {name}: their answers count again and they are served again.",
        "success",
    )
    return _back()


@bp.route("/submissions", methods=["POST"])
@role_required("curator")
def check_submissions() -> str:
    """Paste the participant ids Prolific lists as awaiting review: each gets approve / reject / unknown."""
    text = request.form.get("participants", "")
    participants = text.replace(",", " ").split()
    if not participants:
        raise TaskError("Paste the Prolific participant ids to check (one per line)")
    if len(participants) > MAX_CARD_IDS:
        raise TaskError(f"Expected at most {MAX_CARD_IDS} participant ids, got {len(participants)}")
    study = request.form.get("study", "").strip() or None
    with read_only():
        checks = check_prolific_submissions(participants, study)
    approve = [c.participant for c in checks if c.decision == "approve"]
    flash(
        f"Checked {len(checks)} submissions: {len(approve)} to approve, "
        f"{sum(c.decision == 'reject' for c in checks)} to reject, "
        f"{sum(c.decision == 'unknown' for c in checks)} unknown.",
        "success",
    )
    return render_template("annotation/submissions.html", checks=checks, approve=approve, study=study)


@bp.route("/batches/<int:batch_id>/answers.csv")
@role_required("curator")
def answers_csv(batch_id: int) -> Response:
    """Every answer of the batch, as ``keystone crowd export`` writes answers.csv."""
    with read_only():
        batch = db.session.get(Batch, batch_id)
        if batch is None:
            abort(404, f"No batch {batch_id}.")
        rows = answer_rows(batch)
    buffer = io.StringIO()
    write_spreadsheet_csv(buffer, ANSWER_COLUMNS, rows)  # opened in spreadsheets: formula-like cells neutralised
    response = Response(buffer.getvalue(), mimetype="text/csv")
    response.headers["Content-Disposition"] = f'attachment; filename="batch-{batch_id}-answers.csv"'
    return response
