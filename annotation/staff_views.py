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
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from flask import abort, current_app, flash, redirect, render_template, request, url_for
from flask_login import current_user
from markupsafe import Markup
from sqlalchemy import func, select
from werkzeug.wrappers import Response

from core.auth import role_required
from core.db import db, read_only
from core.limits import parse_positive_int, parse_whole_number
from core.models import Card
from core.spreadsheet_csv import write_spreadsheet_csv

from .batches import AlreadyCreated, confirm_gold, create_batch, waiting_card_ids
from .blueprint import bp
from .cli import ANSWER_COLUMNS, answer_rows
from .labels import (
    DEFAULT_INVITE_DAYS,
    MAX_INVITE_DAYS,
    batch_labels,
    clean_batch_name,
    invite_statuses,
    name_batch,
    record_invite,
    revoke_invite,
    set_batch_state,
)
from .models import TASK_KINDS, Batch, CrowdSession, Worker
from .progress import AGREEMENT_MIN_ANSWERS, LOW_AGREEMENT, batch_progress, worker_progress
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


def invite_qr_svg(link: str) -> Markup:
    """The invite link as an inline SVG QR code (segno, made here: no third-party image service
    ever sees the link, which is the annotator's whole credential)."""
    import segno

    buffer = io.BytesIO()
    segno.make(link, error="m").save(
        buffer, kind="svg", scale=4, border=4, xmldecl=False, svgns=True, svgclass="invite-qr", lineclass=None
    )
    return Markup(buffer.getvalue().decode("ascii"))


@dataclass
class NewBatchForm:
    """What the new-batch form holds: the values as typed, and an error per field that refused."""

    values: dict[str, str] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    status: int = 400  # 404 when what refused is a card id that names no card

    @classmethod
    def defaults(cls, waiting: Mapping[str, int]) -> NewBatchForm:
        kind = "judge"
        return cls(
            {
                "kind": kind,
                "name": "",
                "cards": "",
                "answers_per_item": "3",
                "gold_rate": "0.1",
                # ticked only when the queue holds cards no open batch has yet: a second submit
                # right after the first would otherwise ask for the same cards again
                "from_review": "1" if waiting.get(kind) else "",
            }
        )


def _invite_rows() -> list[dict[str, Any]]:
    workers = [
        w
        for w in db.session.scalars(
            select(Worker).where(Worker.provider == "invite", Worker.person_id.is_(None)).order_by(Worker.id.desc())
        )
        if not w.external_id.startswith("sim-")
    ]
    statuses = invite_statuses([w.id for w in workers])
    rows = []
    for worker in workers:
        status = statuses[worker.id]
        link = url_for("crowd.invite", token=worker.token, _external=True)
        state = status.state()
        rows.append(
            {
                "worker": worker,
                "link": link,
                "state": state,
                "expires_at": status.expires_at,
                "revoked_at": status.revoked_at,
                "qr": invite_qr_svg(link) if state == "active" else None,
            }
        )
    return rows


def _batches_page(form: NewBatchForm | None = None, status: int = 200) -> tuple[str, int]:
    with read_only():
        batch_rows = list(db.session.scalars(select(Batch).order_by(Batch.id.desc())))
        rows = [batch_progress(b) for b in batch_rows]
        labels = batch_labels([b.id for b in batch_rows])
        workers = {w.id: w for w in db.session.scalars(select(Worker))}
        waiting = {kind: len(waiting_card_ids(kind)) for kind in TASK_KINDS}
        prolific = (
            db.session.scalar(select(func.count()).select_from(CrowdSession).where(CrowdSession.provider == "prolific")) or 0
        )
        page = render_template(
            "annotation/batches.html",
            batches=rows,
            labels=labels,
            workers=workers,
            crowd=worker_progress(),
            invites=_invite_rows(),
            waiting=waiting,
            form=form or NewBatchForm.defaults(waiting),
            prolific_sessions=prolific,
            kinds=TASK_KINDS,
            configured=bool(current_app.config.get("KEYSTONE_PROLIFIC_COMPLETION_CODE")),
            submission_checks=None,
            batch_request_key=secrets.token_urlsafe(18),
            invite_days=DEFAULT_INVITE_DAYS,
            max_invite_days=MAX_INVITE_DAYS,
            low_agreement=LOW_AGREEMENT,
            agreement_min_answers=AGREEMENT_MIN_ANSWERS,
        )
    return page, status


@bp.route("/batches")
@role_required("curator")
def batches() -> tuple[str, int]:
    return _batches_page()


def _read_new_batch(form: NewBatchForm) -> tuple[list[int], str, int, float, str]:
    """The form's cards, kind, N, gold rate and name; each refusal lands on ``form.errors``."""
    kind = form.values["kind"]
    if kind not in TASK_KINDS:
        form.errors["kind"] = f"Expected one of {', '.join(TASK_KINDS)}"
        kind = "judge"
    n, gold_rate, name = 3, 0.1, ""
    try:
        n = _number("answers_per_item", "3", int, 1, 50)
    except TaskError as exc:
        form.errors["answers_per_item"] = exc.message
    try:
        gold_rate = _number("gold_rate", "0.1", float, 0.0, 1.0)
    except TaskError as exc:
        form.errors["gold_rate"] = exc.message
    try:
        name = clean_batch_name(form.values["name"])
    except TaskError as exc:
        form.errors["name"] = exc.message
    ids: list[int] = []
    try:
        ids = _card_ids(form.values["cards"])
    except TaskError as exc:
        form.errors["cards"] = exc.message
    if ids and "cards" not in form.errors:
        with read_only():
            found = set(db.session.scalars(select(Card.id).where(Card.id.in_(ids))))
        missing = [c for c in dict.fromkeys(ids) if c not in found]
        if missing:
            shown = ", ".join(map(str, missing[:10])) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
            form.errors["cards"] = f"No card with id {shown}"
            form.status = 404
    if form.values["from_review"] and "kind" not in form.errors:
        with read_only():
            ids += [c for c in waiting_card_ids(kind) if c not in ids]
    if not ids and "cards" not in form.errors:
        form.errors["cards"] = "No cards: list card ids, or tick the waiting cards (there must be some)"
    return ids, kind, n, gold_rate, name


@bp.route("/batches/new", methods=["POST"])
@role_required("curator")
def new_batch() -> Response | tuple[str, int]:
    fields = ("kind", "name", "cards", "answers_per_item", "gold_rate", "from_review")
    # what was typed comes back into the form as it was (capped: the field takes 10,000 ids)
    form = NewBatchForm({name: request.form.get(name, "")[:200_000] for name in fields})
    # the cards list's bulk form ticks cards: one "cards" field per card
    form.values["cards"] = " ".join(request.form.getlist("cards"))[:200_000]
    form.values["kind"] = form.values["kind"] or "judge"
    ids, kind, n, gold_rate, name = _read_new_batch(form)
    if form.errors:
        return _batches_page(form, form.status if set(form.errors) == {"cards"} else 400)
    key = request.form.get("request_key") or None
    if key is not None and not REQUEST_KEY.fullmatch(key):
        raise TaskError("This form is out of date: reload the batches page and submit it again")
    gold: dict[int, dict[str, bool]] = {}
    shown: dict[int, dict[str, bool]] = {}
    if kind == "confirm":
        with read_only():
            gold, shown = confirm_gold(exclude=ids)  # every grid hides gold
    try:
        batch = create_batch(ids, kind, n, gold_rate, gold=gold, shown=shown, created_by=current_user.id, request_key=key)
    except AlreadyCreated as done:
        flash(
            f"This form was already submitted: it made batch {done.batch_id}, so no new batch was created. "
            "To make another batch, fill in the form again.",
            "info",
        )
        return redirect(url_for("crowd.batches", _anchor=f"batch-{done.batch_id}"), code=303)
    except TaskError as exc:  # e.g. a confirm card nobody proposed a way up for
        form.errors["cards"] = exc.message
        return _batches_page(form, exc.status)
    if name:
        name_batch(batch.id, name, current_user)
    progress = batch_progress(batch)
    flash(
        f"Batch {batch.id}{f' ({name})' if name else ''} created: {progress['items']} {kind} cards, {n} answers each "
        f"({progress['answers_needed']} answers needed). Annotators with an invite link get it on their next visit.",
        "success",
    )
    return redirect(url_for("crowd.batches", _anchor=f"batch-{batch.id}"), code=303)


@bp.route("/batches/<int:batch_id>/name", methods=["POST"])
@role_required("curator")
def rename_batch(batch_id: int) -> Response:
    name = name_batch(batch_id, request.form.get("name", "")[:1000], current_user)
    flash(f"Batch {batch_id} is now called {name!r}." if name else f"Batch {batch_id} has no name now.", "success")
    return redirect(url_for("crowd.batches", _anchor=f"batch-{batch_id}"), code=303)


STATE_WORDS = {
    "paused": "paused: it gives no new tasks (tasks already handed out can still be answered). Resume it when you are ready",
    "open": "open again: annotators get its cards on their next visit",
    "closed": "closed: it gives no new tasks, and its unanswered cards can go into a new batch",
}


@bp.route("/batches/<int:batch_id>/state", methods=["POST"])
@role_required("curator")
def batch_state(batch_id: int) -> Response:
    state = request.form.get("state", "")
    set_batch_state(batch_id, state[:20], current_user)
    flash(f"Batch {batch_id} is {STATE_WORDS.get(state, state)}.", "success")
    return redirect(url_for("crowd.batches", _anchor=f"batch-{batch_id}"), code=303)


@bp.route("/invites", methods=["POST"])
@role_required("curator")
def new_invite() -> Response:
    name = request.form.get("name", "").strip()
    if not name or len(name) > 120 or any(c in name for c in "\r\n\t"):
        raise TaskError("Expected the annotator's name: 1 to 120 characters on one line")
    days = _number("days", str(DEFAULT_INVITE_DAYS), int, 1, MAX_INVITE_DAYS)
    worker = InviteProvider.invite(name)
    expires_at = record_invite(worker, days, current_user)
    flash(
        f"Invite link for {name} made; it works until {expires_at:%Y-%m-%d %H:%M} UTC. "
        "Copy it or show its QR code below and send it to them: it is their login.",
        "success",
    )
    return redirect(url_for("crowd.batches", _anchor=f"invite-{worker.id}"), code=303)


@bp.route("/invites/<int:worker_id>/revoke", methods=["POST"])
@role_required("curator")
def revoke_invite_link(worker_id: int) -> Response:
    worker = revoke_invite(worker_id, current_user)
    flash(
        f"Invite link of {worker.external_id} revoked: it now shows a page saying so, and their open task page "
        "takes no more answers (their answers so far are kept).",
        "success",
    )
    return redirect(url_for("crowd.batches", _anchor="invites"), code=303)


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
