"""The catalogue: a paged, filterable list of cards, one page per card, and their images.

Images are served by card id and a name recorded in the database, never from a path a request
controls. Browsers cannot show TIFF or 16-bit scans, so the original is shown through a JPEG
derived once and cached by content hash under ``DATA_DIR/previews``. Image URLs carry
``?v=<version>``: a response to the current version is cacheable for a year (``immutable``);
any other URL must revalidate with its ETag, so a rerun stage never leaves a stale image pinned.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flask import Blueprint, abort, current_app, redirect, render_template, request, url_for
from flask_login import current_user
from sqlalchemy import ColumnElement, Text, and_, cast, false, func, not_, or_, select
from sqlalchemy.orm import selectinload
from werkzeug.wrappers import Response

from core.auth import add_nav_link, role_home, role_required
from core.db import db, read_only
from core.http_images import not_modified, send_image, url_version
from core.limits import DATABASE_ID_MAX, parse_positive_int
from core.models import CARD_STATES, Card, Collection, MetadataRecord, StageResult
from pipeline.errors import ImageReadError
from pipeline.io import atomic_write, encode_jpeg, read_image

# Stages whose status is a stage result the catalogue can filter on in SQL.
FILTERABLE_STAGES: tuple[str, ...] = ("filter", "rectify", "disparity", "grade", "views")

bp = Blueprint("catalog", __name__, template_folder="templates")

STAFF_ROLES = ("curator", "exporter")  # and admin, who passes every role check
STAGE_FILTER_STATUSES = ("done", "skipped", "failed", "pending")

DISPLAY_MAX_SIDE = 1600
THUMB_MAX_SIDE = 320
# Bump when the way previews are made changes: it is part of their ETag and URL version.
PREVIEW_VERSION = "1"
ARTIFACT_IMAGE_TYPES = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".webp": "image/webp",
    ".gif": "image/gif",
}

bp.record_once(lambda state: add_nav_link(state.app, "Cards", "catalog.cards", *STAFF_ROLES, order=10, home_of=("admin",)))


# ----------------------------------------------------------------------------- loaders


def get_card_or_404(card_id: int, *, with_results: bool = True) -> Card:
    query = select(Card).where(Card.id == card_id).options(selectinload(Card.collection))
    if with_results:
        query = query.options(selectinload(Card.stage_results))
    card = db.session.scalar(query)
    if card is None:
        abort(404, f"There is no card {card_id}.")
    return card


def get_collection_or_404(collection_id: int) -> Collection:
    collection = db.session.get(Collection, collection_id)
    if collection is None:
        abort(404, f"There is no collection {collection_id}.")
    return collection


def data_dir() -> Path:
    return Path(current_app.config["KEYSTONE_DATA_DIR"]).resolve()


def inside_data_dir(relative: str) -> Path:
    """The absolute path of a recorded ``relative`` path, or 404 if it would leave the data dir.

    Checked on the normalised path, not the resolved one: ``..`` or an absolute path in a
    record is refused, while an operator's symlink inside the data dir (originals on another
    disk) keeps working.
    """
    root = data_dir()
    path = Path(os.path.normpath(root / relative))
    if not path.is_relative_to(root) or path == root:
        abort(404, "This file is not in the data folder.")
    return path


# ----------------------------------------------------------------------------- filters


# The longest search the cards list runs; a longer one is cut here and the page says so.
MAX_SEARCH = 200


@dataclass(frozen=True)
class CardFilters:
    collection_id: int | None = None
    state: str | None = None
    stage: str | None = None
    status: str | None = None
    page: int = 1
    search: str = ""
    search_cut: bool = False  # the search as typed was longer than MAX_SEARCH

    def query_args(self, **changes: Any) -> dict[str, Any]:
        """Query-string arguments for a link to these filters with ``changes`` applied."""
        args = {
            "q": self.search,
            "collection": self.collection_id,
            "state": self.state,
            "stage": self.stage,
            "status": self.status,
            "page": self.page,
        }
        args.update(changes)
        return {key: value for key, value in args.items() if value not in (None, "") and (key, value) != ("page", 1)}


def parse_filters(args: Any) -> CardFilters:
    """Read the query string; a value that names nothing is a 400 that says what is allowed."""

    def choice(name: str, allowed: tuple[str, ...]) -> str | None:
        value = (args.get(name) or "").strip()
        if value and value not in allowed:
            abort(400, f"Unknown {name} {value!r}; expected one of {', '.join(allowed)}.")
        return value or None

    def positive_int(name: str) -> int | None:
        value = (args.get(name) or "").strip()
        if not value:
            return None
        try:
            return parse_positive_int(value, name)  # ids and pages within the database's range
        except ValueError as exc:
            abort(400, str(exc))

    stage, status = choice("stage", FILTERABLE_STAGES), choice("status", STAGE_FILTER_STATUSES)
    if status and not stage:
        abort(400, "A status filter needs a stage too, e.g. ?stage=filter&status=done.")
    # Control and formatting characters (PostgreSQL refuses NUL in text) and runs of spaces: one space.
    typed = " ".join("".join(c if c.isprintable() else " " for c in args.get("q") or "").split())
    return CardFilters(
        search=typed[:MAX_SEARCH],
        search_cut=len(typed) > MAX_SEARCH,
        collection_id=positive_int("collection"),
        state=choice("state", CARD_STATES),
        stage=stage,
        status=status,
        page=positive_int("page") or 1,
    )


def stage_status_condition(stage: str, status: str) -> ColumnElement[bool]:
    """SQL for "the card's latest ``stage`` result has ``status``", as ``keystone cards`` reports it.

    No result means pending, except where ``runs.card_state`` derives a skip: stages
    after the filter for a culled card, stages after a failed rectification, and views for a card
    graded failure. (Judge, crop and review are people's work, not stage results; the review
    queue and the crowd pages filter those.)
    """
    from runs.card_state import DOWNSTREAM_OF_CULL, DOWNSTREAM_OF_RECTIFY

    def latest(column: Any, of_stage: str) -> Any:
        return (
            select(column)
            .where(StageResult.card_id == Card.id, StageResult.stage == of_stage)
            .order_by(StageResult.id.desc())
            .limit(1)
            .correlate(Card)
            .scalar_subquery()
        )

    latest_status = latest(StageResult.status, stage)
    derived_skip = Card.state == "culled" if stage in DOWNSTREAM_OF_CULL else false()
    if stage in DOWNSTREAM_OF_RECTIFY:
        # coalesce: a card with no result must compare false, not NULL, or NOT(...) drops it.
        derived_skip = or_(derived_skip, func.coalesce(latest(StageResult.status, "rectify"), "") == "failed")
    if stage == "views":
        derived_skip = or_(derived_skip, func.coalesce(latest(StageResult.outcome, "grade"), "") == "failure")
    if status == "pending":
        return and_(latest_status.is_(None), not_(derived_skip))
    if status == "skipped":
        return or_(latest_status == "skipped", and_(latest_status.is_(None), derived_skip))
    return latest_status == status


def _like_pattern(text: str) -> str:
    """``%text%`` for LIKE with ``\\`` as the escape character: ``%`` and ``_`` in the search are literal."""
    return "%" + text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"


def search_condition(search: str) -> ColumnElement[bool]:
    """SQL for "the card matches ``search``": its id (``12`` or ``#12``), or the text, ignoring
    case, anywhere in its accession number, file name, title or any other catalogue field (the
    card's own metadata and the metadata CSV rows matched to it). Bound parameters only.

    The catalogue fields are JSON columns, searched as their JSON text: SQLite stores non-ASCII
    letters and quotes escaped (``\\u00e9``, ``\\"``), so the search's JSON-escaped spellings are
    tried too. Case is ignored for ASCII letters on SQLite (its LIKE), for all on PostgreSQL (ILIKE).
    Field names match as well (a search for ``title`` finds every card with a title).
    """
    plain = _like_pattern(search)
    # Only the escaped spellings in JSON text: a bare backslash would match every escaped quote.
    spellings = dict.fromkeys([json.dumps(search)[1:-1], json.dumps(search, ensure_ascii=False)[1:-1]])
    in_json = [_like_pattern(spelling) for spelling in spellings]

    def any_like(column: Any, patterns: list[str]) -> ColumnElement[bool]:
        return or_(*(column.ilike(pattern, escape="\\") for pattern in patterns))

    records = (
        select(MetadataRecord.id)
        .where(
            MetadataRecord.card_id == Card.id,
            or_(
                any_like(MetadataRecord.accession, [plain]),
                any_like(MetadataRecord.file_name, [plain]),
                any_like(cast(MetadataRecord.fields, Text), in_json),
            ),
        )
        .correlate(Card)
        .exists()
    )
    conditions = [
        any_like(Card.accession, [plain]),
        any_like(Card.source_name, [plain]),
        any_like(cast(Card.source_metadata, Text), in_json),
        records,
    ]
    number = search.removeprefix("#")
    if number.isascii() and number.isdigit() and len(number) <= 18:
        card_id = int(number)
        if 1 <= card_id <= DATABASE_ID_MAX:
            conditions.insert(0, Card.id == card_id)
    return or_(*conditions)


def filter_conditions(filters: CardFilters, *, with_state: bool = True) -> list[ColumnElement[bool]]:
    conditions: list[ColumnElement[bool]] = []
    if filters.search:
        conditions.append(search_condition(filters.search))
    if filters.collection_id is not None:
        conditions.append(Card.collection_id == filters.collection_id)
    if filters.stage and filters.status:
        conditions.append(stage_status_condition(filters.stage, filters.status))
    if with_state and filters.state:
        conditions.append(Card.state == filters.state)
    return conditions


# ----------------------------------------------------------------------------- pages


@bp.route("/")
def index() -> Any:
    if not current_user.is_authenticated:
        return redirect(url_for("auth.login"))
    # Each role lands where its work starts (a curator on Review, an exporter on Releases, an
    # annotator with an account on My tasks, an admin on Cards); someone with no role is welcomed.
    home = role_home()
    if home is not None:
        return redirect(home)
    return render_template("catalog/home.html")


@bp.route("/cards")
@role_required(*STAFF_ROLES)
def cards() -> Any:
    filters = parse_filters(request.args)
    per_page = int(current_app.config.get("CATALOG_PAGE_SIZE", 48))
    with read_only():
        collection = get_collection_or_404(filters.collection_id) if filters.collection_id else None
        conditions = filter_conditions(filters)
        total = db.session.scalar(select(func.count()).select_from(Card).where(*conditions)) or 0
        pages = max(1, math.ceil(total / per_page))
        if filters.page > pages:
            abort(404, f"Page {filters.page} is past the last page ({pages}).")
        page_cards = list(
            db.session.scalars(
                select(Card)
                .where(*conditions)
                .order_by(Card.id)
                .offset((filters.page - 1) * per_page)
                .limit(per_page)
                .options(selectinload(Card.stage_results), selectinload(Card.collection))
            )
        )
        state_counts = dict(
            db.session.execute(
                select(Card.state, func.count()).where(*filter_conditions(filters, with_state=False)).group_by(Card.state)
            ).all()
        )
        collections = list(db.session.scalars(select(Collection).order_by(Collection.name)))
        return render_template(
            "catalog/cards.html",
            cards=page_cards,
            filters=filters,
            total=total,
            page=filters.page,
            pages=pages,
            per_page=per_page,
            collection=collection,
            collections=collections,
            states=CARD_STATES,
            state_counts={state: state_counts.get(state, 0) for state in CARD_STATES},
            stages=FILTERABLE_STAGES,
            statuses=STAGE_FILTER_STATUSES,
            max_search=MAX_SEARCH,
            bulk=_bulk_form(),
        )


# A feature above the catalogue (the crowd) takes the ticked cards: named by endpoint, never
# imported, and offered only where that feature is installed and the person may use it.
BULK_ENDPOINT, BULK_ROLE = "crowd.new_batch", "curator"


def _bulk_form() -> dict[str, str] | None:
    if BULK_ENDPOINT not in current_app.view_functions or not current_user.has_role(BULK_ROLE):
        return None
    return {"action": url_for(BULK_ENDPOINT), "request_key": secrets.token_urlsafe(18)}


@bp.route("/cards/<int:card_id>")
@role_required(*STAFF_ROLES)
def card_page(card_id: int) -> Any:
    from runs.card_state import card_state

    with read_only():
        card = get_card_or_404(card_id)
        state = card_state(card)
        latest = card.latest_results()
        filter_result = latest.get("filter")
        rectify_result = latest.get("rectify")
        disparity_result = latest.get("disparity")
        records = list(
            db.session.scalars(select(MetadataRecord).where(MetadataRecord.card_id == card.id).order_by(MetadataRecord.id))
        )
        return render_template(
            "catalog/card.html",
            card=card,
            filter_result=filter_result,
            rectify_result=rectify_result,
            disparity_result=disparity_result,
            grade_result=latest.get("grade"),
            views_result=latest.get("views"),
            stereo_downloads=stereo_downloads(card, rectify_result, disparity_result),
            filter_view=FilterView.of(card, filter_result) if filter_result is not None else None,
            statuses=state.statuses,
            orientation=state.orientation,
            state_sentence=state.sentence,
            history=list(reversed(card.stage_results)),
            records=records,
        )


# ----------------------------------------------------------------------------- filter metrics


def _box(value: Any) -> tuple[float, float, float, float] | None:
    if isinstance(value, (list, tuple)) and len(value) == 4 and all(isinstance(v, (int, float)) for v in value):
        x0, y0, x1, y1 = (float(v) for v in value)
        if x1 > x0 and y1 > y0:
            return x0, y0, x1, y1
    return None


@dataclass(frozen=True)
class FilterView:
    """What the card page shows of a filter result: boxes for the overlay and metric rows."""

    canvas: tuple[int, int]  # (width, height) of the decoded original, the boxes' coordinates
    left_box: tuple[float, float, float, float] | None
    right_box: tuple[float, float, float, float] | None
    rows: list[tuple[str, str]]
    thresholds: dict[str, Any] | None
    other: dict[str, Any]

    @classmethod
    def of(cls, card: Card, result: StageResult) -> FilterView:
        metrics = dict(result.metrics or {})
        size = metrics.get("card_size")
        if isinstance(size, list) and len(size) == 2 and all(isinstance(v, (int, float)) and v > 0 for v in size):
            canvas = (int(size[0]), int(size[1]))
        else:
            canvas = (card.width, card.height)
        rows, used = filter_metric_rows(metrics, result.seconds)
        thresholds = filter_thresholds(result)
        shown = used | set(thresholds or ())
        other = {key: value for key, value in metrics.items() if key not in shown}
        return cls(
            canvas=canvas,
            left_box=_box(metrics.get("left_box")),
            right_box=_box(metrics.get("right_box")),
            rows=rows,
            thresholds=thresholds,
            other=other,
        )


def _number(value: Any, digits: int = 0) -> str:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "—" if value is None else str(value)
    return f"{value:,.{digits}f}"


def _duration(value: Any) -> str:
    if not isinstance(value, (int, float)):
        return "—"
    return f"{value * 1000:,.0f} ms" if value < 1 else f"{value:,.2f} s"


def filter_metric_rows(metrics: dict[str, Any], total_seconds: float | None) -> tuple[list[tuple[str, str]], set[str]]:
    """Label/value rows for the filter's metrics; also the keys they used."""
    rows: list[tuple[str, str]] = []
    used: set[str] = set()
    fraction = metrics.get("good_match_fraction")
    denominator = metrics.get("denominator")
    if isinstance(denominator, str) and isinstance(metrics.get(denominator), (int, float)):
        denominator_text = f"{denominator} = {_number(metrics[denominator])}"
    elif isinstance(denominator, (int, float)):
        denominator_text = _number(denominator)
    else:
        denominator_text = "not recorded"
    if isinstance(fraction, (int, float)):
        value = f"{fraction * 100:.2f} %"
        if isinstance(metrics.get("good_matches"), (int, float)):
            value += f" = {_number(metrics['good_matches'])} good matches / {denominator_text}"
        rows.append(("Good-match fraction", value))
    rows.append(("Denominator", denominator_text))
    rows.append(("Good matches (ratio test)", _number(metrics.get("good_matches"))))
    rows.append(("Keypoints, left half", _number(metrics.get("keypoints_left"))))
    rows.append(("Keypoints, right half", _number(metrics.get("keypoints_right"))))
    rows.append(("Detection time", _duration(metrics.get("detect_seconds"))))
    rows.append(("Matching time", _duration(metrics.get("match_seconds"))))
    rows.append(("Total time for the card", _duration(total_seconds)))
    used.update(
        {
            "good_match_fraction",
            "denominator",
            "good_matches",
            "keypoints_left",
            "keypoints_right",
            "detect_seconds",
            "match_seconds",
            "thresholds",
            "left_box",
            "right_box",
            "card_size",
        }
    )
    for key, label in (("left_box", "Left box [x0, y0, x1, y1]"), ("right_box", "Right box [x0, y0, x1, y1]")):
        if key in metrics:
            rows.append(
                (label, ", ".join(_number(v) for v in metrics[key]) if isinstance(metrics[key], list) else str(metrics[key]))
            )
    return rows, used


def filter_thresholds(result: StageResult) -> dict[str, Any] | None:
    """The thresholds the result was computed with, or None when they cannot be known here.

    In order: a ``thresholds`` dict in the metrics; the current parameters when their hash is
    the one recorded; else whichever parameter fields the stage copied into its metrics.
    """
    metrics = result.metrics or {}
    if isinstance(metrics.get("thresholds"), dict):
        return dict(metrics["thresholds"])
    from dataclasses import asdict, is_dataclass

    from pipeline.records import param_hash
    from runs.specs import available_stages

    spec = available_stages().get(result.stage)
    if spec is None or not is_dataclass(spec.params):
        return None
    if param_hash(spec.params) == result.param_hash:
        return asdict(spec.params)
    recorded = {name: metrics[name] for name in asdict(spec.params) if name in metrics}
    return recorded or None


# ----------------------------------------------------------------------------- images


@bp.app_template_global()
def card_title(card: Card) -> str:
    metadata = card.source_metadata or {}
    return str(metadata.get("title") or metadata.get("Title") or card.accession or card.source_name)


@bp.app_template_global()
def fit_within(width: int, height: int, side: int) -> tuple[int, int]:
    """Size of a ``width`` x ``height`` image shrunk (never enlarged) to fit a ``side`` square."""
    scale = min(1.0, side / max(width, height, 1))
    return max(1, round(width * scale)), max(1, round(height * scale))


def preview_etag(content_hash: str, variant: str) -> str:
    return f"{content_hash}-{variant}-{PREVIEW_VERSION}"


def artifact_etag(card: Card, result: StageResult, name: str) -> str:
    detail = f"{result.stage}\0{name}\0{result.artifacts.get(name)}\0{result.code_version}"
    return f"{card.content_hash}-{result.param_hash}-{hashlib.sha256(detail.encode()).hexdigest()[:12]}"


@bp.app_template_global()
def card_image_url(card: Card, variant: str = "original") -> str:
    """URL of a card's display image (``original``) or thumbnail (``thumb``), versioned."""
    etag = preview_etag(card.content_hash, "display" if variant == "original" else "thumb")
    endpoint = "catalog.original_image" if variant == "original" else "catalog.thumb_image"
    return url_for(endpoint, card_id=card.id, v=url_version(etag))


@bp.app_template_global()
def image_artifacts(result: StageResult | None) -> list[str]:
    """The names of ``result``'s artifacts a page can show as images (the filter also records
    its matches as a ``.npy``: listing every artifact put a broken image on every card page)."""
    if result is None:
        return []
    return [
        name
        for name, relative in (result.artifacts or {}).items()
        if isinstance(relative, str) and Path(relative).suffix.lower() in ARTIFACT_IMAGE_TYPES
    ]


@bp.app_template_global()
def artifact_image_url(card: Card, result: StageResult, name: str) -> str:
    return url_for(
        "catalog.artifact_image", card_id=card.id, stage=result.stage, name=name, v=url_version(artifact_etag(card, result, name))
    )


_UNWRITABLE_PREVIEW_FOLDERS: set[str] = set()


def ensure_previews(content_hash: str, stored_path: str) -> dict[str, Path | bytes]:
    """Make the display JPEG (<= 1600 px) and thumbnail (<= 320 px) once; the original is decoded once.

    Each is the cached file, or the JPEG itself when the cache cannot be written (a read-only
    data folder, a full disk): the image is still shown, made again on each request until the
    folder is writable (a warning in the log says why).
    """
    folder = data_dir() / "previews"
    targets: dict[str, Path | bytes] = {"display": folder / f"{content_hash}.jpg", "thumb": folder / f"{content_hash}.thumb.jpg"}
    missing = {variant: path for variant, path in targets.items() if isinstance(path, Path) and not path.exists()}
    if missing:
        original = inside_data_dir(stored_path)
        if not original.is_file():
            abort(404, "The original file of this card is missing from the data folder.")
        try:
            image = read_image(original, max_pixels=int(current_app.config["KEYSTONE_MAX_PIXELS"]))
        except ImageReadError as exc:
            abort(404, f"The original cannot be shown: {exc.reason()}")
        for variant, path in missing.items():
            payload = encode_jpeg(image, max_side=DISPLAY_MAX_SIDE if variant == "display" else THUMB_MAX_SIDE, quality=88)
            try:
                with atomic_write(path) as handle:
                    handle.write(payload)
            except OSError as exc:
                if str(folder) not in _UNWRITABLE_PREVIEW_FOLDERS:  # once per folder, not per image
                    _UNWRITABLE_PREVIEW_FOLDERS.add(str(folder))
                    current_app.logger.warning("Serving card previews without their cache: cannot write %s (%s)", path, exc)
                targets[variant] = payload
    return targets


def _preview_response(card_id: int, variant: str) -> Response:
    with read_only():
        card = get_card_or_404(card_id, with_results=False)
        content_hash, stored_path = card.content_hash, card.stored_path
    etag = preview_etag(content_hash, variant)
    cached = not_modified(etag)
    if cached is not None:
        return cached
    path = ensure_previews(content_hash, stored_path)[variant]
    return send_image(path, "image/jpeg", etag)


@bp.route("/cards/<int:card_id>/image/original")
@role_required(*STAFF_ROLES)
def original_image(card_id: int) -> Response:
    return _preview_response(card_id, "display")


@bp.route("/cards/<int:card_id>/image/thumb")
@role_required(*STAFF_ROLES)
def thumb_image(card_id: int) -> Response:
    return _preview_response(card_id, "thumb")


@bp.route("/cards/<int:card_id>/image/<stage>/<name>")
@role_required(*STAFF_ROLES)
def artifact_image(card_id: int, stage: str, name: str) -> Response:
    """An image a stage recorded for this card, by the name in its latest result of that stage."""
    with read_only():
        card = get_card_or_404(card_id)
        result = card.latest_results().get(stage)
        if result is None:
            abort(404, f"Card {card_id} has no {stage!r} result.")
        relative = (result.artifacts or {}).get(name)
        if not isinstance(relative, str) or not relative:
            abort(404, f"The latest {stage!r} result of card {card_id} has no artifact called {name!r}.")
        etag = artifact_etag(card, result, name)
    mimetype = ARTIFACT_IMAGE_TYPES.get(Path(relative).suffix.lower())
    if mimetype is None:
        abort(404, f"Artifact {name!r} is not an image this page can show.")
    cached = not_modified(etag)
    if cached is not None:
        return cached
    path = inside_data_dir(relative)
    if not path.is_file():
        abort(404, f"Artifact {name!r} is recorded but its file is missing; rerun the {stage} stage.")
    return send_image(path, mimetype, etag)


# ----------------------------------------------------------------------------- stereo downloads


def _stereo_inputs(rectify: StageResult | None, disparity: StageResult | None) -> tuple[str, str, str] | None:
    """The rectified views and the left disparity (paths under the data dir), or None when the
    card has no finished rectified pair with a disparity."""
    if rectify is None or rectify.status not in ("done", "skipped") or disparity is None or disparity.status != "done":
        return None
    paths = (
        (rectify.artifacts or {}).get("left"),
        (rectify.artifacts or {}).get("right"),
        (disparity.artifacts or {}).get("disparity_left"),
    )
    if not all(isinstance(path, str) and path for path in paths):
        return None
    return paths  # type: ignore[return-value]


def _stereo_etag(card: Card, inputs: tuple[str, str, str], rectify: StageResult, disparity: StageResult) -> str:
    from pipeline.stereo_files import CardCaption

    caption = CardCaption.of(card.source_metadata or {}, card.accession, card.source_name)
    detail = "\0".join(
        [
            *inputs,
            rectify.param_hash,
            rectify.code_version,
            disparity.param_hash,
            disparity.code_version,
            repr(caption),
            STEREO_DOWNLOAD_VERSION,
        ]
    )
    return f"{card.content_hash[:16]}-stereo-{hashlib.sha256(detail.encode()).hexdigest()[:16]}"


STEREO_DOWNLOAD_VERSION = "1"  # bump when the way the stereo files are made changes


def stereo_downloads(card: Card, rectify: StageResult | None, disparity: StageResult | None) -> list[dict[str, str]]:
    """Links to the card's stereo files (anaglyph, wiggles, side-by-side, JPS, MPO), or none
    when it has no rectified pair with a disparity yet."""
    from pipeline.stereo_files import STEREO_FORMATS

    inputs = _stereo_inputs(rectify, disparity)
    if inputs is None or rectify is None or disparity is None:
        return []
    version = url_version(_stereo_etag(card, inputs, rectify, disparity))
    return [
        {
            "name": name,
            "file": file_name,
            "what": what,
            "url": url_for("catalog.stereo_download", card_id=card.id, fmt=name, v=version),
        }
        for name, (file_name, _mime, what) in STEREO_FORMATS.items()
    ]


@bp.route("/cards/<int:card_id>/stereo/<fmt>")
@role_required(*STAFF_ROLES)
def stereo_download(card_id: int, fmt: str) -> Response:
    """One stereo file of a card, made from its latest rectified pair and disparity on first
    request and cached under ``DATA_DIR/stereo_downloads`` by the inputs' fingerprint."""
    import numpy as np

    from pipeline.stereo_files import STEREO_FORMATS, CardCaption, encode_stereo
    from pipeline.stereo_formats import StereoFormatError

    if fmt not in STEREO_FORMATS:
        abort(404, f"There is no stereo format {fmt!r}; formats: {', '.join(STEREO_FORMATS)}.")
    file_name, mimetype, _what = STEREO_FORMATS[fmt]
    with read_only():
        card = get_card_or_404(card_id)
        latest = card.latest_results()
        rectify, disparity = latest.get("rectify"), latest.get("disparity")
        inputs = _stereo_inputs(rectify, disparity)
        if inputs is None or rectify is None or disparity is None:
            abort(404, f"Card {card_id} has no rectified pair with a disparity yet: run the rectify and disparity stages.")
        etag = _stereo_etag(card, inputs, rectify, disparity)
        caption = CardCaption.of(card.source_metadata or {}, card.accession, card.source_name)
        download_name = f"card-{card.id:05d}-{file_name}"
    cached = not_modified(etag)
    if cached is None:
        target = data_dir() / "stereo_downloads" / f"{etag}-{file_name}"
        if target.is_file():
            payload = target.read_bytes()
        else:
            left_path, right_path, disparity_path = (inside_data_dir(path) for path in inputs)
            if not (left_path.is_file() and right_path.is_file() and disparity_path.is_file()):
                abort(404, "The rectified pair or its disparity is recorded but missing on disk; rerun those stages.")
            try:
                max_pixels = int(current_app.config["KEYSTONE_MAX_PIXELS"])
                left, right = read_image(left_path, max_pixels), read_image(right_path, max_pixels)
                disparity_map = np.load(disparity_path, allow_pickle=False)
                payload = encode_stereo(left, right, disparity_map, caption, only=(fmt,))[fmt]
            except (ImageReadError, StereoFormatError, OSError, ValueError) as exc:
                abort(404, f"The {fmt} file of card {card_id} cannot be made: {exc}")
            try:
                with atomic_write(target) as handle:
                    handle.write(payload)
            except OSError as exc:  # a read-only data folder still serves the file, made per request
                current_app.logger.warning("Serving a stereo file without its cache: cannot write %s (%s)", target, exc)
        response = send_image(payload, mimetype, etag)
    else:
        response = cached
    response.headers["Content-Disposition"] = f'attachment; filename="{download_name}"'
    return response
