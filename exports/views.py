"""The releases page: the list of releases, a dry-run preview of the next one, and publishing.

For exporters (and admins). Releases made here go to ``KEYSTONE_RELEASES_DIR`` (default
``<data dir>/releases``); the release's README, CHANGELOG, croissant.json and SHA256SUMS
can be read from the list.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from flask import (
    Blueprint,
    Response,
    abort,
    current_app,
    flash,
    redirect,
    render_template,
    url_for,
)
from flask_login import current_user
from flask_wtf import FlaskForm
from sqlalchemy import select
from sqlalchemy.orm import defer
from wtforms import SelectField, SelectMultipleField, TextAreaField
from wtforms.fields.choices import SelectChoice
from wtforms.validators import DataRequired, Length
from wtforms.widgets import CheckboxInput, ListWidget

from app.auth import add_nav_link, role_required
from app.db import db, read_only

from .models import Release
from .records import DEFAULT_FORMATS, FORMATS, RELEASABLE_GRADES

bp = Blueprint("exports", __name__, url_prefix="/releases", template_folder="templates")
bp.record_once(lambda state: add_nav_link(state.app, "Releases", "exports.index", "exporter", order=70))

RELEASE_DOCUMENTS = {"README.md": "text/markdown", "CHANGELOG.md": "text/markdown",
                     "croissant.json": "application/json", "SHA256SUMS": "text/plain"}


class ReleaseForm(FlaskForm):
    min_grade = SelectField("Lowest grade", choices=[SelectChoice(g, f"{g} artifacts") for g in RELEASABLE_GRADES], default="some")
    formats = SelectMultipleField("Formats", choices=list(FORMATS), default=list(DEFAULT_FORMATS),
                                  validators=[DataRequired("Choose at least one format.")],
                                  widget=ListWidget(prefix_label=False), option_widget=CheckboxInput())
    notes = TextAreaField("Notes", validators=[Length(max=5000)])


def releases_dir() -> Path:
    configured = current_app.config.get("KEYSTONE_RELEASES_DIR")
    return Path(configured) if configured else Path(current_app.config["KEYSTONE_DATA_DIR"]) / "releases"


def _releases() -> list[Release]:
    with read_only():
        rows = list(db.session.scalars(select(Release).options(defer(Release.stats), defer(Release.changes))
                                       .order_by(Release.id.desc())))
        summaries = {row.id: db.session.scalar(select(Release.stats["grades"]).where(Release.id == row.id))
                     for row in rows}
        for row in rows:
            row.grade_counts = summaries.get(row.id) or {}  # type: ignore[attr-defined]
            db.session.expunge(row)
    return rows


@bp.route("/")
@role_required("exporter")
def index() -> Any:
    return render_template("exports/index.html", releases=_releases(), form=ReleaseForm(), preview=None)


@bp.route("/preview", methods=["POST"])
@role_required("exporter")
def preview() -> Any:
    from .release import plan_release

    form = ReleaseForm()
    if not form.validate_on_submit():
        return render_template("exports/index.html", releases=_releases(), form=form, preview=None), 400
    plan = plan_release(min_grade=form.min_grade.data, formats=tuple(form.formats.data), notes=form.notes.data or "")
    return render_template("exports/index.html", releases=_releases(), form=form, preview=plan)


@bp.route("/publish", methods=["POST"])
@role_required("exporter")
def publish() -> Any:
    from .release import ReleaseError, publish_release

    form = ReleaseForm()
    if not form.validate_on_submit():
        return render_template("exports/index.html", releases=_releases(), form=form, preview=None), 400
    # The logged-in person is already loaded and detached (app.auth): using it opens no
    # transaction, so the export's reads do not hold SQLite's write lock for minutes.
    actor = current_user._get_current_object()
    try:
        report = publish_release(releases_dir(), min_grade=form.min_grade.data, formats=tuple(form.formats.data),
                                 notes=form.notes.data or "", actor=actor, actor_label="web")
    except ReleaseError as exc:
        db.session.rollback()
        flash(str(exc), "error")
        return render_template("exports/index.html", releases=_releases(), form=form, preview=None), 409
    flash(f"Published release {report.version}: {report.cards} cards, {report.files} files in {report.path}.", "success")
    return redirect(url_for("exports.index"))


@bp.route("/<version>/<name>")
@role_required("exporter")
def document(version: str, name: str) -> Response:
    if name not in RELEASE_DOCUMENTS:
        abort(404, f"Releases show {', '.join(RELEASE_DOCUMENTS)}; {name!r} is not one of them.")
    with read_only():
        path = db.session.scalar(select(Release.path).where(Release.version == version))
    if path is None:
        abort(404, f"There is no release {version}.")
    target = Path(path) / name
    if not target.is_file():
        abort(404, f"{name} of release {version} is not on disk at {path}.")
    return Response(target.read_bytes(), mimetype=RELEASE_DOCUMENTS[name] + "; charset=utf-8")
