"""Curator review pages: the queue, one page per card with its decision keys, history, disputes.

Every route needs the curator role (admins pass). Decisions are POSTs with the CSRF token and
the review version the curator saw (a hidden form field, or ``version`` in a JSON body sent
with the ``X-CSRFToken`` header by the page's script); a stale version is refused with 409 and
a sentence naming who changed the card and when. The anaglyph is rendered here from the
rectified previews and cached by the browser with an ETag.
"""

from __future__ import annotations

import hashlib
import io
import math
from typing import Any
from urllib.parse import unquote, urlsplit

import numpy as np
from flask import (
    Blueprint,
    abort,
    current_app,
    flash,
    jsonify,
    redirect,
    render_template,
    request,
    session,
    url_for,
)
from flask_login import current_user
from sqlalchemy import select
from sqlalchemy.orm import selectinload
from werkzeug.wrappers import Response

from annotation import questions as question_table
from annotation.models import Aggregate, Worker
from core.auth import add_nav_link, role_required
from core.db import db, read_only
from core.json_body import load_json_body
from core.limits import parse_positive_int
from core.models import Collection
from core.security import safe_next

from . import run_hooks
from .held_back import held_back, held_back_cards
from .models import GRADE_NAMES, GRADES, CardReview
from .plain_words import certainty_words, crowd_reason_words, grade_reason_words, orientation_evidence_words
from .tasks import (
    ACTIONS,
    QUEUE_DECISIONS,
    SEND_BACK_KINDS,
    CardHeldBack,
    QueueFilters,
    ReviewConflict,
    ReviewError,
    aggregate_answers,
    bulk_decide,
    card_history,
    card_results_digest,
    crowd_view,
    decide,
    disputed_aggregates,
    grade_reasons,
    queue_neighbours,
    redo_decision,
    resolve_aggregate,
    review_queue,
    sync_reviews,
    undo_decision,
)
from .threshold_table import threshold_table

bp = Blueprint(
    "review",
    __name__,
    url_prefix="/review",
    template_folder="templates",
    static_folder="static",
    static_url_path="/review-static",
)
bp.record_once(lambda state: add_nav_link(state.app, "Review", "review.queue", "curator", order=30, home_of=("curator",)))
bp.record_once(lambda state: run_hooks.register(state.app))


@bp.app_template_global()
def queue_thumb_url(row: Any) -> str:
    """The catalogue's cached thumbnail (<= 320 px JPEG, versioned URL cached for a year) of a queue row."""
    from catalogue.views import preview_etag
    from core.http_images import url_version

    return url_for("catalog.thumb_image", card_id=row.card_id, v=url_version(preview_etag(row.content_hash, "thumb")))


ANAGLYPH_VERSION = "1"  # part of the anaglyph's ETag: bump when the way it is made changes
DISPUTES_SHOWN = 50


@bp.errorhandler(ReviewError)
def review_error(error: ReviewError) -> Any:
    db.session.rollback()
    # A card held back by a dispute: the answer links to the dispute, which leads back to the card.
    dispute_url = None
    if isinstance(error, CardHeldBack) and error.dispute_ids:
        try:
            filters = _filters(request.args).query_args()  # the queue's, kept on the way back
        except ReviewError:
            filters = {}
        dispute_url = dispute_link(error.dispute_ids[0], error.card_id, **filters)
    if request.is_json or request.accept_mimetypes.best == "application/json":
        body: dict[str, Any] = {"code": error.status, "message": error.message}
        if dispute_url is not None:
            body["dispute_url"] = dispute_url
        return jsonify({"error": body}), error.status
    return render_template(
        "review/message.html",
        title="Not saved" if error.status == 409 else "Cannot do that",
        message=error.message,
        conflict=isinstance(error, ReviewConflict),
        dispute_url=dispute_url,
    ), error.status


@bp.app_template_global()
def dispute_link(aggregate_id: int, card_id: int, **filters: Any) -> str:
    """The page of a dispute on a card, returning to that card's review page once it is settled
    (``filters``: the queue's filters the card page was opened with, kept on the way back)."""
    return url_for("review.dispute", aggregate_id=aggregate_id, next=url_for("review.card", card_id=card_id, **filters))


def review_return_path(target: str | None) -> str | None:
    """``target`` if it is a page of review on this site (a path under /review/), else None.

    Where a settled dispute sends the curator back to: only ever a review page, so a crafted
    link cannot turn the dispute page into an open redirect (:func:`core.security.safe_next`
    refuses other hosts and schemes) or send a curator elsewhere on the site through "..".
    """
    path = safe_next(target)
    if path is None:
        return None
    route = urlsplit(path).path
    # Browsers resolve "." and ".." segments, percent-encoded ones too ("%2e%2e").
    if not route.startswith("/review/") or any(unquote(part) in (".", "..") for part in route.split("/")):
        return None
    return path


def _curator() -> Any:
    return current_user._get_current_object()  # the detached Person row: id and username


def _filters(args: Any) -> QueueFilters:
    collection = (args.get("collection") or "").strip()
    try:
        collection_id = parse_positive_int(collection, "collection") if collection else None
    except ValueError as exc:
        raise ReviewError(str(exc)) from None
    return QueueFilters(
        grade=(args.get("grade") or "").strip() or None,
        collection_id=collection_id,
        reason=(args.get("reason") or "").strip() or None,
        decision=(args.get("decision") or "").strip() or "pending",
    )


def _page_number(args: Any, name: str = "page") -> int:
    try:
        return parse_positive_int(args.get(name) or "1", name)
    except ValueError as exc:
        raise ReviewError(str(exc)) from None


# ----------------------------------------------------------------------------- the queue


@bp.route("/")
@role_required("curator")
def queue() -> Any:
    filters = _filters(request.args)
    page = _page_number(request.args)
    per_page = int(current_app.config.get("REVIEW_PAGE_SIZE", 50))
    with read_only():
        result = review_queue(
            filters.grade, filters.collection_id, filters.reason, filters.decision, limit=per_page, offset=(page - 1) * per_page
        )
        pages = max(1, math.ceil(result.total / per_page))
        if page > pages:
            abort(404, f"Page {page} is past the last page ({pages}).")
        # One batch for the page, not a query per row: paging stays linear.
        held = held_back_cards(row.card_id for row in result.rows)
        disputes, dispute_total = disputed_aggregates(limit=DISPUTES_SHOWN)
        collections = list(db.session.scalars(select(Collection).order_by(Collection.name)))
        return render_template(
            "review/queue.html",
            result=result,
            filters=filters,
            page=page,
            pages=pages,
            collections=collections,
            grades=GRADES,
            grade_names=GRADE_NAMES,
            decisions=QUEUE_DECISIONS,
            actions=ACTIONS,
            kinds=SEND_BACK_KINDS,
            held=held,
            disputes=disputes,
            dispute_total=dispute_total,
        )


@bp.route("/sync", methods=["POST"])
@role_required("curator")
def sync() -> Response:
    report = sync_reviews()
    flash(
        f"Synced with the grader: {report.created} new, {report.updated} regraded, {report.reopened} back from "
        f"the crowd, {report.decided_changed} decided cards with a new automatic grade.",
        "success",
    )
    return redirect(url_for("review.queue"), code=303)


def _bulk_items(values: list[str]) -> list[tuple[int, int]]:
    items = []
    for value in values:
        review_id, _, version = value.partition(":")
        try:
            items.append((parse_positive_int(review_id, "review"), parse_positive_int(version, "version")))
        except ValueError:
            raise ReviewError(f"Expected selected cards as review:version, got {value[:80]!r}") from None
    return items


@bp.route("/bulk", methods=["POST"])
@role_required("curator")
def bulk() -> Any:
    body = load_json_body() if request.is_json else None
    source: Any = body if body is not None else request.form
    if body is not None:
        items = body.get("items", [])
        if not isinstance(items, list):
            raise ReviewError(f"Expected items as a list of {{review, version}}, got {type(items).__name__}")
        values = [f"{item.get('review')}:{item.get('version')}" for item in items if isinstance(item, dict)]
    else:
        values = request.form.getlist("item")
    action = str(source.get("action") or "")
    outcomes = bulk_decide(
        _bulk_items(values),
        action,
        curator=_curator(),
        grade=source.get("grade") or None,
        note=str(source.get("note") or ""),
        kind=str(source.get("kind") or "crop"),
    )
    if body is not None:
        return jsonify({"outcomes": [o.as_json() for o in outcomes]})
    applied = [o for o in outcomes if o.status == "applied"]
    flash(
        f"{action.replace('_', ' ').capitalize()}: applied to {len(applied)} of {len(outcomes)} cards.",
        "success" if len(applied) == len(outcomes) else "info",
    )
    for outcome in outcomes:
        if outcome.status != "applied":
            flash(outcome.message, "error")
    return redirect(url_for("review.queue", **_filters(request.args).query_args()), code=303)


# ----------------------------------------------------------------------------- one card


def _crowd_boxes(view: Any) -> list[dict[str, Any]]:
    """Boxes for the SVG overlay in original pixels: each answer thin, the aggregate thick."""
    boxes = []
    for answer in view.crop_answers:
        for half in ("left", "right"):
            box = (answer.payload or {}).get(half)
            if isinstance(box, list) and len(box) == 4:
                boxes.append({"half": half, "box": box, "kind": "answer", "flagged": answer.flagged})
    if view.crop is not None:
        for half in ("left", "right"):
            box = (view.crop.label or {}).get(half)
            if isinstance(box, list) and len(box) == 4:
                boxes.append({"half": half, "box": box, "kind": "aggregate", "flagged": False})
    return boxes


def _judgement_counts(answers: list[Any]) -> dict[str, tuple[int, int]]:
    """Per judge question the answers asked (annotation.questions): how many said yes, of how many."""
    counts = {}
    for question in question_table.asked(question_table.judge_questions(), (a.payload for a in answers)):
        said = [a for a in answers if not question.optional or question.key in (a.payload or {})]
        counts[question.key] = (sum(1 for a in said if (a.payload or {}).get(question.key) is True), len(said))
    return counts


@bp.route("/cards/<int:card_id>")
@role_required("curator")
def card(card_id: int) -> Any:
    from catalogue.views import get_card_or_404
    from runs.card_state import card_state

    filters = _filters(request.args)
    with read_only():
        card = get_card_or_404(card_id)
        state = card_state(card)
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
        latest = card.latest_results()
        grade_result = None
        if review is not None and review.auto_param_hash:
            grade_result = next(
                (r for r in card.stage_results if r.stage == "grade" and r.param_hash == review.auto_param_hash), None
            )
        previous, following = queue_neighbours(card_id, filters)
        view = crowd_view(card_id)
        orientation_panel = _orientation_panel(card, state.orientation)
        return render_template(
            "review/card.html",
            card=card,
            review=review,
            rectify=latest.get("rectify"),
            disparity=latest.get("disparity"),
            views_result=latest.get("views"),
            grade_result=grade_result,
            reasons=grade_reasons(grade_result),
            crowd=view,
            crowd_boxes=_crowd_boxes(view),
            judgements=_judgement_counts(view.judge_answers),
            previous=previous,
            following=following,
            filters=filters,
            grades=GRADES,
            grade_names=GRADE_NAMES,
            kinds=SEND_BACK_KINDS,
            anaglyph_url=_anaglyph_url(card, latest.get("rectify")),
            table=threshold_table(grade_result.metrics) if grade_result is not None else None,
            # the sentence beside a review too while its results are stale, recomputed or recomputing:
            # that is what the curator waits for
            state_sentence=state.sentence
            if review is None or state.stale or state.recomputing or state.outdated_acceptance or state.withdrawn
            else "",
            # a decided card is held back from a new accept or grade as much as a pending one
            held=held_back(state) if review is not None else None,
            orientation_panel=orientation_panel,
            results_digest=card_results_digest(card),
            crowd_words=_crowd_words(view),
            certainty_words=certainty_words,
            grade_reason_words=grade_reason_words,
            orientation_evidence_words=orientation_evidence_words,
        )


def _crowd_words(view: Any) -> list[str]:
    """Why the crowd's answers on the card wait for a curator, in words (review.plain_words)."""
    lines = []
    for aggregate in (view.judge, view.crop):
        if aggregate is not None and aggregate.state == "needs_curator" and aggregate.reasons:
            lines += crowd_reason_words(aggregate.reasons, aggregate.label if aggregate.kind == "judge" else None)
    return lines


def _orientation_panel(card: Any, orientation: dict[str, Any]) -> dict[str, Any]:
    """What the card page's orientation form shows: the orientation in use (``orientation``,
    from :mod:`runs.card_state`), the step's probabilities and evidence, and the curator's
    current override."""
    from .models import OrientationOverride

    step = card.latest_results().get("orientation")
    override = db.session.scalar(select(OrientationOverride).where(OrientationOverride.card_id == card.id))
    return {
        "orientation": orientation,
        "step": step.metrics.get("flags") if step is not None and step.status == "done" else None,
        "step_reason": step.reason if step is not None else None,
        "override": {flag: getattr(override, flag) for flag in ("upside_down", "inverted", "swapped")}
        if override is not None
        else {},
    }


@bp.route("/cards/<int:card_id>/orientation", methods=["POST"])
@role_required("curator")
def orientation_card(card_id: int) -> Any:
    """A curator's override of the card's orientation flags (yes / no / empty = leave it to the
    step and the crowd); recorded with an audit event. Form POST with the CSRF token."""
    from .orientation import override_orientation

    flags = {flag: request.form.get(flag, "") for flag in ("upside_down", "inverted", "swapped")}
    after = override_orientation(card_id, flags, curator=_curator(), note=str(request.form.get("note") or ""))
    state = ", ".join(
        f"{flag} {'yes' if after[flag] else 'no' if after[flag] is False else '?'}"
        for flag in ("upside_down", "inverted", "swapped")
    )
    flash(
        f"Card {card_id}: orientation {state}"
        + (f" (decided by {after['decided_by']})" if after["decided_by"] else " (still undecided)")
        + (
            "; the background worker recomputes its rectification with it now, and the card comes back to the queue."
            if _worker_alive()
            else "; no background worker is running: `keystone worker` or `keystone run` recomputes its rectification."
        ),
        "success",
    )
    return redirect(url_for("review.card", card_id=card_id, **_filters(request.args).query_args()), code=303)


def _worker_alive() -> bool:
    from runs.card_state import live_worker

    with read_only():
        return live_worker() is not None


def _next_url(card_id: int, filters: QueueFilters) -> str:
    with read_only():
        _, following = queue_neighbours(card_id, filters)
    if following is None:
        return url_for("review.queue", **filters.query_args())
    return url_for("review.card", card_id=following, **filters.query_args())


@bp.route("/cards/<int:card_id>/decide", methods=["POST"])
@role_required("curator")
def decide_card(card_id: int) -> Any:
    body = load_json_body() if request.is_json else None
    source: Any = body if body is not None else request.form
    try:
        version = parse_positive_int(source.get("version"), "version")
    except ValueError as exc:
        raise ReviewError(f"Expected the version of the review you saw: {exc}") from None
    with read_only():
        review_id = db.session.scalar(select(CardReview.id).where(CardReview.card_id == card_id))
    if review_id is None:
        raise ReviewError(f"Card {card_id} has no review yet: it has not been graded (or the queue is not synced)", 404)
    action, grade = str(source.get("action") or ""), source.get("grade") or None
    if body is None and request.form.get("choice"):
        # The page's buttons without script: "accept", "change:few", "send_back", ...
        action, _, grade = request.form["choice"].partition(":")
        grade = grade or None
    decided = decide(
        review_id,
        action,
        expected_version=version,
        curator=_curator(),
        grade=grade,
        note=str(source.get("note") or ""),
        kind=str(source.get("kind") or "crop"),
        # the digest of the results the page showed: a decision is given those, not newer ones
        shown_results=str(source.get("results")) if source.get("results") else None,
    )
    next_url = _next_url(card_id, _filters(request.args))
    _offer_undo(decided)
    if body is not None:
        return jsonify(
            {
                "card": decided.card_id,
                "decision": decided.decision,
                "grade": decided.grade,
                "version": decided.version,
                "batch": decided.batch_id,
                "next_url": next_url,
            }
        )
    return redirect(next_url, code=303)


DECISION_WORDS = {
    "accepted": "accepted",
    "changed": "grade changed",
    "sent_back": "sent back to the crowd",
    "rejected": "rejected",
    "pending": "back to pending",
}


def _offer_undo(decided: Any) -> None:
    """The confirmation the next page shows (base.html): what was done, an Undo button that
    posts the version this decision left, and after a send-back the new batch with its link."""
    message = f"Card {decided.card_id}: {DECISION_WORDS.get(decided.decision, decided.decision)}"
    if decided.grade:
        message += f" as {GRADE_NAMES[decided.grade]}"
    link = None
    if decided.batch_id:
        message += f"; it is in new crowd batch {decided.batch_id}, waiting for annotators"
        link = {
            "url": url_for("crowd.batches") + f"#batch-{decided.batch_id}",
            "text": f"Open batch {decided.batch_id} (invite links, progress)",
        }
    session["keystone_undo"] = {
        "message": message + ".",
        "link": link,
        "action": url_for("review.undo", card_id=decided.card_id),
        "fields": {"version": decided.version},
    }


def _review_and_version(card_id: int, verb: str) -> tuple[int, int]:
    """The card's review id and the form's ``version`` for an undo or a redo; a ReviewError (400,
    or 404 when the card has no review) otherwise."""
    try:
        version = parse_positive_int(request.form.get("version") or "", "version")
    except ValueError as exc:
        raise ReviewError(str(exc)) from None
    with read_only():
        review_id = db.session.scalar(select(CardReview.id).where(CardReview.card_id == card_id))
    if review_id is None:
        raise ReviewError(f"Card {card_id} has no review, so no decision to {verb}", 404)
    return review_id, version


@bp.route("/cards/<int:card_id>/undo", methods=["POST"])
@role_required("curator")
def undo(card_id: int) -> Any:
    review_id, version = _review_and_version(card_id, "undo")
    restored = undo_decision(review_id, expected_version=version, curator=_curator())
    flash(
        f"Undone: card {card_id} is {DECISION_WORDS.get(restored.decision, restored.decision)} again"
        + (f" ({GRADE_NAMES[restored.grade]})" if restored.grade else "")
        + ".",
        "success",
    )
    # The bar the next page shows (base.html) offers the decision back, once.
    session["keystone_undo"] = {
        "message": f"Card {card_id}: changed your mind again?",
        "link": None,
        "action": url_for("review.redo", card_id=card_id),
        "fields": {"version": restored.version},
        "button": "Redo",
    }
    return redirect(url_for("review.card", card_id=card_id), code=303)


@bp.route("/cards/<int:card_id>/redo", methods=["POST"])
@role_required("curator")
def redo(card_id: int) -> Any:
    review_id, version = _review_and_version(card_id, "redo")
    decided = redo_decision(review_id, expected_version=version, curator=_curator())
    _offer_undo(decided)
    return redirect(url_for("review.card", card_id=card_id), code=303)


@bp.route("/cards/<int:card_id>/history")
@role_required("curator")
def history(card_id: int) -> Any:
    from catalogue.views import get_card_or_404

    with read_only():
        card = get_card_or_404(card_id, with_results=False)
        return render_template("review/history.html", card=card, events=card_history(card_id))


# ----------------------------------------------------------------------------- anaglyph


def _anaglyph_etag(card: Any, rectify: Any) -> str:
    from catalogue.views import artifact_etag

    parts = [artifact_etag(card, rectify, name) for name in ("left_preview", "right_preview")]
    return hashlib.sha256("\0".join([*parts, ANAGLYPH_VERSION]).encode()).hexdigest()[:32]


def _anaglyph_url(card: Any, rectify: Any) -> str | None:
    from core.http_images import url_version as _version

    artifacts = (rectify.artifacts or {}) if rectify is not None else {}
    if not (artifacts.get("left_preview") and artifacts.get("right_preview")):
        return None
    return url_for("review.anaglyph", card_id=card.id, v=_version(_anaglyph_etag(card, rectify)))


def red_cyan_anaglyph(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """A grey red/cyan anaglyph, ``(H, W, 3)`` uint8: red = left view's luma, green = blue = right's.

    Grey rather than colour anaglyph: colours of the scene would otherwise leak between the
    eyes (retinal rivalry on red or cyan objects). Inputs are ``(H, W)`` or ``(H, W, 3)``
    uint8 RGB; when the previews differ in size by rounding, both are cut to the common
    top-left region (rectified views share their pixel grid, so rows stay aligned).
    """

    def luma(image: np.ndarray) -> np.ndarray:
        if image.ndim == 2:
            return image
        # ITU-R BT.601 weights, as PIL's "L" conversion uses.
        return np.clip(image[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) + 0.5, 0, 255).astype(
            np.uint8
        )

    if left.size == 0 or right.size == 0:
        raise ValueError(f"Expected two non-empty views, got shapes {left.shape} and {right.shape}")
    height, width = min(left.shape[0], right.shape[0]), min(left.shape[1], right.shape[1])
    red, cyan = luma(left)[:height, :width], luma(right)[:height, :width]
    return np.stack([red, cyan, cyan], axis=2)


@bp.route("/cards/<int:card_id>/anaglyph.png")
@role_required("curator")
def anaglyph(card_id: int) -> Response:
    from PIL import Image

    from catalogue.views import get_card_or_404, inside_data_dir
    from core.http_images import cache_headers as _cache_headers, not_modified as _not_modified
    from pipeline.errors import ImageReadError
    from pipeline.io import read_image

    with read_only():
        card = get_card_or_404(card_id)
        rectify = card.latest_results().get("rectify")
        artifacts = (rectify.artifacts or {}) if rectify is not None else {}
        if not (artifacts.get("left_preview") and artifacts.get("right_preview")):
            abort(404, f"Card {card_id} has no rectified pair to make an anaglyph from.")
        etag = _anaglyph_etag(card, rectify)
        paths = [inside_data_dir(artifacts[name]) for name in ("left_preview", "right_preview")]
    cached = _not_modified(etag)
    if cached is not None:
        return cached
    try:
        views = [read_image(path) for path in paths]
    except (ImageReadError, OSError) as exc:
        abort(404, f"The rectified previews of card {card_id} cannot be read; rerun the rectify stage ({exc}).")
    buffer = io.BytesIO()
    Image.fromarray(red_cyan_anaglyph(*views)).save(buffer, format="PNG", compress_level=3)
    response = Response(buffer.getvalue(), mimetype="image/png")
    response.set_etag(etag)
    response = response.make_conditional(request)
    _cache_headers(response, etag)
    return response


# ----------------------------------------------------------------------------- disputes


CONFIDENT_POSTERIOR = 0.9  # below this the crowd's label is not offered as the default answer


def judge_questions_asked(aggregate: Any, answers: list[Any]) -> dict[str, str]:
    """The judge questions (annotation.questions) a disputed judgement was asked, key -> how a
    curator reads it: the required ones, and an optional one (``swapped``) where an answer or
    the crowd's label has it."""
    payloads = [*(a.payload for a in answers), aggregate.label]
    return {q.key: q.review for q in question_table.asked(question_table.judge_questions(), payloads)}


def _label_from_form(kind: str, form: Any, questions: dict[str, str]) -> dict[str, Any]:
    if kind == "judge":
        label = {}
        for question, words in questions.items():
            raw = (form.get(question) or "").strip().lower()
            if raw not in ("yes", "no"):
                raise ReviewError(f"Choose yes or no for whether the card is {words}")
            label[question] = raw == "yes"
        return label
    label: dict[str, Any] = {}
    for half in ("left", "right"):
        box = []
        for corner in ("x0", "y0", "x1", "y1"):
            raw = (form.get(f"{half}_{corner}") or "").strip()
            if not raw:
                raise ReviewError(f"Draw the {half} box on the card (or type its {corner})")
            try:
                value = float(raw)
            except ValueError:
                raise ReviewError(f"Expected a number for the {half} box {corner}, got {raw!r}") from None
            if not math.isfinite(value):
                raise ReviewError(f"Expected a finite number for the {half} box {corner}, got {raw!r}")
            box.append(value)
        label[half] = box
    return label


def _dispute_page(aggregate_id: int, back_to: str | None, error: str | None = None, status: int = 200) -> Any:
    from catalogue.views import get_card_or_404

    with read_only():
        aggregate = db.session.get(Aggregate, aggregate_id)
        if aggregate is None:
            abort(404, f"There is no crowd aggregate {aggregate_id}.")
        card = get_card_or_404(aggregate.card_id, with_results=False)
        answers = aggregate_answers(aggregate)
        questions = judge_questions_asked(aggregate, answers) if aggregate.kind == "judge" else {}
        view = crowd_view(card.id)
        boxes = []
        if aggregate.kind == "crop":
            view.crop, view.crop_answers = aggregate, answers
            boxes = _crowd_boxes(view)
        workers = {
            w.id: w
            for w in db.session.scalars(
                select(Worker).where(Worker.id.in_({a.worker_id for a in answers})).options(selectinload(Worker.person))
            )
        }
        return render_template(
            "review/dispute.html",
            aggregate=aggregate,
            card=card,
            answers=answers,
            boxes=boxes,
            judgements=_judgement_counts(answers) if aggregate.kind == "judge" else {},
            workers={wid: worker_label(w) for wid, w in workers.items()},
            questions=questions,
            defaults=judge_defaults(aggregate, questions),
            posterior=posterior_words(aggregate),
            error=error,
            form=request.form,
            back_to=back_to,
        ), status


def worker_label(worker: Any) -> str:
    """A worker as a curator knows them: the person's name, else the invite name or provider id."""
    if worker.person is not None:
        return worker.person.display_name or worker.person.username
    provider = {"invite": "invite link", "prolific": "Prolific", "mturk": "MTurk"}.get(worker.provider, worker.provider)
    return f"{worker.external_id} ({provider})"


def _yes_probability(aggregate: Any, question: str) -> float | None:
    value = (aggregate.posterior or {}).get(question)
    if isinstance(value, list) and len(value) == 2 and all(isinstance(p, (int, float)) for p in value):
        return float(value[1])
    return None


def judge_defaults(aggregate: Any, questions: dict[str, str]) -> dict[str, str | None]:
    """The answer to pre-select per question of ``questions``: the crowd's label only where its
    posterior is at least :data:`CONFIDENT_POSTERIOR`; otherwise None, and the curator must choose."""
    if aggregate.kind != "judge":
        return {}
    defaults: dict[str, str | None] = {}
    for question in questions:
        yes = _yes_probability(aggregate, question)
        label = (aggregate.label or {}).get(question)
        if yes is None or not isinstance(label, bool):
            defaults[question] = None
            continue
        sure = yes if label else 1.0 - yes
        defaults[question] = ("yes" if label else "no") if sure >= CONFIDENT_POSTERIOR else None
    return defaults


def posterior_words(aggregate: Any) -> list[str]:
    """The crowd model's belief in words: "upside down: 25 % likely yes"."""
    if aggregate.kind == "judge":
        words = []
        for question in question_table.judge_questions():
            yes = _yes_probability(aggregate, question.key)
            if yes is not None:
                words.append(f"{question.review}: {100 * yes:.0f} % likely")
        return words
    words = []
    for half in ("left", "right"):
        entry = (aggregate.posterior or {}).get(half)
        if isinstance(entry, dict):
            iou = entry.get("mean_iou")
            kept, dropped = entry.get("kept"), entry.get("dropped")
            part = f"{half} box: "
            part += f"{len(kept) if isinstance(kept, list) else kept} answers kept" if kept is not None else ""
            if dropped:
                part += f", {len(dropped) if isinstance(dropped, list) else dropped} dropped as outliers"
            if isinstance(iou, (int, float)):
                part += f", mean overlap {100 * iou:.0f} %"
            words.append(part)
    return words


@bp.route("/disputes/<int:aggregate_id>", methods=["GET", "POST"])
@role_required("curator")
def dispute(aggregate_id: int) -> Any:
    """A disputed crowd answer and the curator's own; once saved, back to ``next`` (the card's
    review page the curator came from, :func:`review_return_path`), else to the queue's disputes."""
    back_to = review_return_path(request.args.get("next"))
    if request.method == "GET":
        return _dispute_page(aggregate_id, back_to)
    with read_only():
        aggregate = db.session.get(Aggregate, aggregate_id)
        if aggregate is None:
            abort(404, f"There is no crowd aggregate {aggregate_id}.")
        kind = aggregate.kind
        questions = judge_questions_asked(aggregate, aggregate_answers(aggregate)) if kind == "judge" else {}
    try:
        label = _label_from_form(kind, request.form, questions)
        resolved = resolve_aggregate(
            aggregate_id,
            label,
            curator=_curator(),
            make_gold=request.form.get("make_gold") == "on",
            note=request.form.get("note", ""),
        )
    except ReviewConflict:
        raise
    except ReviewError as exc:
        db.session.rollback()
        return _dispute_page(aggregate_id, back_to, exc.message, exc.status)
    flash(
        f"Card {resolved.card_id}: your {kind} answer is now the card's truth"
        + (" and a gold item for later batches." if resolved.gold_id else "."),
        "success",
    )
    return redirect(back_to or url_for("review.queue") + "#disputes", code=303)
