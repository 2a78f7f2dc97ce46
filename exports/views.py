"""The releases page: the list of releases, a dry-run preview of the next one, and publishing.

For exporters (and admins). Releases made here go to ``KEYSTONE_RELEASES_DIR`` (default
``<data dir>/releases``); the release's README, CHANGELOG, croissant.json and SHA256SUMS
can be read from the list, every file of a release downloaded from its own page, and the
whole release as one tar archive, streamed as it is read.

Publishing publishes exactly what was previewed: the preview carries a digest of its plan
(version, cards and their content digests, formats, notes) and publish refuses, showing what
changed, when the plan it would make now has another digest. A release whose content (cards,
their digests, formats, lowest grade) is the same as the last release's is refused too.
"""

from __future__ import annotations

import hashlib
import json
import tarfile
from collections.abc import Iterator
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
    send_file,
    stream_with_context,
    url_for,
)
from flask_login import current_user
from sqlalchemy import select
from sqlalchemy.orm import defer
from wtforms import (
    HiddenField,
    SelectField,
    SelectMultipleField,
    TextAreaField,
    ValidationError,
)
from wtforms.fields.choices import SelectChoice
from wtforms.validators import Length
from wtforms.widgets import CheckboxInput, ListWidget

from core.auth import add_nav_link, role_required
from core.db import db, read_only
from core.json_body import BrowserForm
from core.limits import parse_positive_int

from .formats import default_format_names, format_names
from .models import Release
from .records import RELEASABLE_GRADES
from .release_words import release_summary, version_reason

bp = Blueprint("exports", __name__, url_prefix="/releases", template_folder="templates")
bp.record_once(lambda state: add_nav_link(state.app, "Releases", "exports.index", "exporter", order=70, home_of=("exporter",)))

FILES_LISTED = 1000  # a release page lists this many files; the archive and SHA256SUMS hold them all
CARDS_LISTED = 50  # added, removed and changed cards named on a page (each list); the CHANGELOG has all
DEFAULT_VERIFY_TIMEOUT_S = 60.0  # KEYSTONE_VERIFY_TIMEOUT_S: a web verify that takes longer is stopped
RELEASE_DOCUMENTS = {
    "README.md": "text/markdown",
    "CHANGELOG.md": "text/markdown",
    "croissant.json": "application/json",
    "SHA256SUMS": "text/plain",
}


class ReleaseForm(BrowserForm):
    min_grade = SelectField(
        "Lowest grade", choices=[SelectChoice(g, f"{g} artifacts") for g in RELEASABLE_GRADES], default="some"
    )
    # No DataRequired: it would put `required` on every checkbox, and a browser then refuses the
    # form unless all of them are ticked. At least one is checked on the server instead.
    formats = SelectMultipleField(
        "Formats",
        choices=list(format_names()),
        default=list(default_format_names()),
        widget=ListWidget(prefix_label=False),
        option_widget=CheckboxInput(),
    )
    notes = TextAreaField("Notes", validators=[Length(max=5000)])
    plan_digest = HiddenField()
    planned_version = HiddenField()
    planned_cards = HiddenField()

    def validate_formats(self, field: Any) -> None:
        if not field.data:
            raise ValidationError("Choose at least one format.")


def plan_digest(plan: Any) -> str:
    """What publishing would write, as one hash: version, lowest grade, formats, notes and each
    card's content digest. Any change between preview and publish changes it."""
    document = {
        "version": plan.version,
        "min_grade": plan.min_grade,
        "formats": sorted(plan.formats),
        "notes": plan.notes,
        "cards": {key: entry.get("digest") for key, entry in plan.manifest.items()},
    }
    return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()


def content_digest(manifest: dict[str, Any], formats: list[str], min_grade: str) -> str:
    """A release's content without its version, date or notes: two releases with the same
    content digest hold the same files for the same cards."""
    document = {
        "min_grade": min_grade,
        "formats": sorted(formats),
        "cards": {key: (entry or {}).get("digest") for key, entry in manifest.items()},
    }
    return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()


def same_as_last_release(plan: Any) -> str | None:
    """The version of the last release when ``plan`` would publish the same content, else None."""
    from .catalogue import latest_release

    with read_only():
        last = latest_release()
        if last is None:
            return None
        manifest = dict((last.stats or {}).get("manifest") or {})
        same = content_digest(manifest, list(last.formats or []), last.min_grade) == content_digest(
            plan.manifest, list(plan.formats), plan.min_grade
        )
        return last.version if same else None


def change_details(changes: dict[str, Any], formats: list[str], min_grade: str) -> dict[str, Any]:
    """What a release (or a preview) changes, for ``exports/_changes.html``: a sentence, why its
    version is what it is, and the added, removed and changed cards with their titles and
    accession numbers (the first :data:`CARDS_LISTED` of each)."""
    from catalogue.views import card_title
    from core.models import Card

    changes = changes or {}
    added, removed = list(changes.get("added") or []), list(changes.get("removed") or [])
    changed = list(changes.get("changed") or [])
    with read_only():
        previous = None
        if changes.get("previous_version"):
            previous = db.session.execute(
                select(Release.formats, Release.min_grade).where(Release.version == changes["previous_version"])
            ).first()
        wanted = {int(i) for i in added[:CARDS_LISTED] + removed[:CARDS_LISTED]} | {
            int(entry["card_id"]) for entry in changed[:CARDS_LISTED]
        }
        cards = {card.id: card for card in db.session.scalars(select(Card).where(Card.id.in_(wanted)))} if wanted else {}
        labels = {card_id: {"title": card_title(card), "accession": card.accession} for card_id, card in cards.items()}

    def listed(card_id: Any, **extra: Any) -> dict[str, Any]:
        label = labels.get(int(card_id))  # a card deleted since is named by its id alone
        return {
            "id": int(card_id),
            "title": label["title"] if label else None,
            "accession": label["accession"] if label else None,
            **extra,
        }

    previous_formats = list(previous.formats or []) if previous is not None else None
    return {
        "previous_version": changes.get("previous_version"),
        "kind": changes.get("kind"),
        "summary": release_summary(changes, formats, previous_formats, min_grade, previous.min_grade if previous else None),
        "version_reason": version_reason(changes, formats, previous_formats),
        "counts": {"added": len(added), "removed": len(removed), "changed": len(changed)},
        "added": [listed(i) for i in added[:CARDS_LISTED]],
        "removed": [listed(i) for i in removed[:CARDS_LISTED]],
        "changed": [listed(entry["card_id"], why=entry.get("why") or []) for entry in changed[:CARDS_LISTED]],
    }


def releases_dir() -> Path:
    configured = current_app.config.get("KEYSTONE_RELEASES_DIR")
    return Path(configured) if configured else Path(current_app.config["KEYSTONE_DATA_DIR"]) / "releases"


def _releases() -> list[Release]:
    with read_only():
        rows = list(
            db.session.scalars(select(Release).options(defer(Release.stats), defer(Release.changes)).order_by(Release.id.desc()))
        )
        summaries = {row.id: db.session.scalar(select(Release.stats["grades"]).where(Release.id == row.id)) for row in rows}
        for row in rows:
            row.grade_counts = summaries.get(row.id) or {}  # type: ignore[attr-defined]
            db.session.expunge(row)
    return rows


@bp.route("/")
@role_required("exporter")
def index() -> Any:
    return render_template("exports/index.html", releases=_releases(), form=ReleaseForm(), preview=None)


@bp.route("/preview", methods=["GET"], endpoint="preview_again")
@bp.route("/publish", methods=["GET"], endpoint="publish_again")
@role_required("exporter")
def back_to_the_form() -> Any:
    # A reload or a bookmark of the preview or publish address (both answer a form's POST) goes
    # back to the form, rather than to the release page "preview/" that the address resembles.
    return redirect(url_for("exports.index"))


@bp.route("/preview", methods=["POST"])
@role_required("exporter")
def preview() -> Any:
    from .release import plan_release

    form = ReleaseForm()
    if not form.validate_on_submit():
        return render_template("exports/index.html", releases=_releases(), form=form, preview=None), 400
    plan = plan_release(min_grade=form.min_grade.data, formats=tuple(form.formats.data), notes=form.notes.data or "")
    return _preview_page(form, plan)


def _preview_page(form: ReleaseForm, plan: Any, *, changed: dict[str, Any] | None = None, status: int = 200) -> Any:
    form.plan_digest.data = plan_digest(plan)
    form.planned_version.data = plan.version
    form.planned_cards.data = ",".join(sorted(plan.manifest, key=int))
    return render_template(
        "exports/index.html",
        releases=_releases(),
        form=form,
        preview=plan,
        story=change_details(plan.changes, list(plan.formats), plan.min_grade),
        identical_to=same_as_last_release(plan),
        changed=changed,
    ), status


def _card_ids(text: str) -> set[int]:
    """The preview's card ids (its hidden field): 400 for anything but ids within the database's range."""
    try:
        return {parse_positive_int(part, "a previewed card id") for part in (text or "").split(",") if part.strip()}
    except ValueError as exc:
        abort(400, f"The preview's list of cards is not a list of card ids ({exc}) Preview the release again.")


class _NotAsPreviewed(Exception):
    """A publish refused because its plan is not the previewed one (or repeats the last release)."""

    def __init__(self, plan: Any, message: str, changed: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.plan, self.message, self.changed = plan, message, changed


@bp.route("/publish", methods=["POST"])
@role_required("exporter")
def publish() -> Any:
    from .release import ReleaseError, plan_release, publish_release

    form = ReleaseForm()
    if not form.validate_on_submit():
        return render_template("exports/index.html", releases=_releases(), form=form, preview=None), 400
    if not form.plan_digest.data:
        flash("Preview the release first: publishing publishes exactly what the preview showed.", "error")
        return render_template("exports/index.html", releases=_releases(), form=form, preview=None), 400

    def exactly_as_previewed(plan: Any) -> None:
        # Called under the publish lock (exports.release): a publish that raced this one has
        # recorded its release by now, so this plan is checked against the catalogue as it is.
        if plan_digest(plan) != form.plan_digest.data:
            before, now = _card_ids(form.planned_cards.data), {int(key) for key in plan.manifest}
            changed = {
                "version_before": form.planned_version.data or "?",
                "version_now": plan.version,
                "added": sorted(now - before),
                "removed": sorted(before - now),
                "same_cards": before == now,
            }
            raise _NotAsPreviewed(
                plan,
                "Nothing was published: the release changed since your preview (see below). "
                "Check the new preview and publish it if it is what you want.",
                changed,
            )
        identical = same_as_last_release(plan)
        if identical:
            raise _NotAsPreviewed(
                plan,
                f"Nothing was published: this release would hold exactly the same cards, files and formats as "
                f"release {identical}. Accept or change cards in review, or choose other formats, first.",
            )

    # The logged-in person is already loaded and detached (core.auth): using it opens no
    # transaction, so the export's reads do not hold SQLite's write lock for minutes.
    actor = current_user._get_current_object()
    try:
        # Checked first outside the lock too, so a stale form is refused before anything on disk
        # is touched (planning is a read; publish_release plans again under its lock).
        exactly_as_previewed(
            plan_release(min_grade=form.min_grade.data, formats=tuple(form.formats.data), notes=form.notes.data or "")
        )
        report = publish_release(
            releases_dir(),
            min_grade=form.min_grade.data,
            formats=tuple(form.formats.data),
            notes=form.notes.data or "",
            actor=actor,
            actor_label="web",
            check=exactly_as_previewed,
        )
    except _NotAsPreviewed as refused:
        db.session.rollback()
        flash(refused.message, "error")
        return _preview_page(form, refused.plan, changed=refused.changed, status=409)
    except ReleaseError as exc:
        db.session.rollback()
        flash(str(exc), "error")
        return render_template("exports/index.html", releases=_releases(), form=form, preview=None), 409
    flash(
        f"Published release {report.version}: {report.cards} card{'' if report.cards == 1 else 's'}, {report.files} files.",
        "success",
    )
    return redirect(url_for("exports.release_page", version=report.version), code=303)


def _release_root(version: str) -> Path:
    with read_only():
        path = db.session.scalar(select(Release.path).where(Release.version == version))
    if path is None:
        abort(404, f"There is no release {version}.")
    root = Path(path)
    if not root.is_dir():
        abort(404, f"Release {version} is not on disk at {path}.")
    return root.resolve()


def release_files(root: Path) -> list[tuple[str, int]]:
    """(path relative to the release, bytes) of every file in it, sorted; links are left out."""
    files = []
    for path in sorted(root.rglob("*")):
        if path.is_file() and not path.is_symlink():
            files.append((path.relative_to(root).as_posix(), path.stat().st_size))
    return files


@bp.route("/<version>/")
@role_required("exporter")
def release_page(version: str, verification: dict[str, Any] | None = None) -> Any:
    root = _release_root(version)
    with read_only():
        release = db.session.scalar(select(Release).where(Release.version == version).options(defer(Release.stats)))
        db.session.expunge(release)
    files = release_files(root)
    return render_template(
        "exports/release.html",
        release=release,
        story=change_details(release.changes, list(release.formats or []), release.min_grade),
        verification=verification,
        files=files[:FILES_LISTED],
        file_count=len(files),
        total=sum(size for _, size in files),
    )


# Runs in a child process, so a check that takes too long can be stopped (a thread cannot be).
_VERIFY_CHILD = (
    "import json, sys\nfrom exports.verify import verify_release\nprint(json.dumps(verify_release(sys.argv[1]).as_json()))\n"
)


def verify_in_child(root: Path, timeout_s: float) -> dict[str, Any]:
    """:func:`exports.verify.verify_release` on ``root`` (the check ``keystone verify`` runs), in a
    child process stopped after ``timeout_s``. Its report (``ok``, ``checked``, ``problems``) plus
    ``seconds``; or ``timed_out``; or ``error`` when the check itself failed."""
    import os
    import subprocess
    import sys
    import time

    package_parent = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [package_parent, os.environ.get("PYTHONPATH")]))}
    clock = time.monotonic()
    try:
        done = subprocess.run(
            [sys.executable, "-c", _VERIFY_CHILD, str(root)], capture_output=True, text=True, timeout=timeout_s, env=env
        )
    except subprocess.TimeoutExpired:
        return {"timed_out": True, "timeout_s": timeout_s}
    seconds = round(time.monotonic() - clock, 1)
    try:
        report = json.loads(done.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
        return {"error": tail[0][:500], "seconds": seconds}
    return {**report, "seconds": seconds}


@bp.route("/<version>/verify", methods=["GET"], endpoint="verify_again")
@role_required("exporter")
def back_to_the_release(version: str) -> Any:
    # A reload or a bookmark of the verify address (it answers the Verify button's POST) goes back
    # to the release's page, rather than to a release file named "verify" (a 404).
    return redirect(url_for("exports.release_page", version=version))


@bp.route("/<version>/verify", methods=["POST"])
@role_required("exporter")
def verify(version: str) -> Any:
    """Check the release on disk as ``keystone verify`` does and show the result on its page."""
    root = _release_root(version)
    timeout_s = float(current_app.config.get("KEYSTONE_VERIFY_TIMEOUT_S", DEFAULT_VERIFY_TIMEOUT_S))
    return release_page(version, verification={**verify_in_child(root, timeout_s), "folder": str(root)})


@bp.route("/<version>/files/<path:name>")
@role_required("exporter")
def release_file(version: str, name: str) -> Response:
    root = _release_root(version)
    try:
        target = (root / name).resolve()
        # Inside the release folder only: "../", absolute paths and links out of it are refused.
        outside = not target.is_relative_to(root) or target == root or (root / name).is_symlink()
        missing = not target.is_file()
    except OSError:  # a name the file system refuses (longer than 255 bytes: ENAMETOOLONG) names no file
        outside, missing = False, True
    if outside:
        abort(404, f"{name[:80]!r} is not a file of release {version}.")
    if missing:
        abort(404, f"Release {version} has no file {name[:80]!r}.")
    return send_file(target, as_attachment=True, download_name=target.name, conditional=True, max_age=3600)


class _Chunks:
    """A write-only file for tarfile's stream mode: what is written is handed on in chunks."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def write(self, data: bytes) -> int:
        self.parts.append(bytes(data))
        return len(data)

    def take(self) -> bytes:
        data, self.parts = b"".join(self.parts), []
        return data


def stream_tar(root: Path, prefix: str) -> Iterator[bytes]:
    """The release folder as an uncompressed tar, one file at a time (never all in memory)."""
    sink = _Chunks()
    with tarfile.open(fileobj=sink, mode="w|", format=tarfile.PAX_FORMAT) as archive:  # type: ignore[arg-type]
        for name, _ in release_files(root):
            path = root / name
            info = archive.gettarinfo(str(path), arcname=f"{prefix}/{name}")
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            with path.open("rb") as handle:
                archive.addfile(info, handle)
            yield sink.take()
    yield sink.take()


@bp.route("/<version>/archive.tar")
@role_required("exporter")
def archive(version: str) -> Response:
    root = _release_root(version)
    name = f"keystone-{version}"
    response = Response(stream_with_context(stream_tar(root, name)), mimetype="application/x-tar")
    response.headers["Content-Disposition"] = f'attachment; filename="{name}.tar"'
    return response


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
