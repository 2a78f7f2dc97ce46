"""Publishing a release: plan (what goes in, what changed, which version), write, move into place.

A release is written into ``<out>/.<version>.partial-XXXX`` (locked while this export runs, see
:mod:`exports.staging`) and renamed to ``<out>/<version>``, world-readable, only when every file,
the Croissant metadata and ``SHA256SUMS`` are complete; any error removes the partial folder and
records nothing, and the folders of exports killed outright are removed by the next export. The same inputs give byte-identical files:
the release's date is the newest review decision among its cards, not the clock.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy.exc import IntegrityError

from core.db import db, read_only
from core.models import Person

from .catalogue import (
    Exclusion,
    eligible_card_ids,
    inputs_date,
    latest_release,
    stream_release_cards,
)
from .croissant import write_croissant
from .models import Release
from .records import (
    DEFAULT_FORMATS,
    Changes,
    compare_manifests,
    grades_at_or_above,
    next_version,
    parse_formats,
)
from .staging import ReleaseStaging, make_world_readable, remove_stale_partials
from .stereo import StereoWriter
from .writers import (
    CardPayload,
    FileLedger,
    KeystoneDepthWriter,
    ParquetWriter,
    ViewsWriter,
    WebDatasetWriter,
    build_payload,
)

MANIFEST_FILES = ("croissant.json", "SHA256SUMS")


class ReleaseError(RuntimeError):
    """Something a user can fix: no accepted cards, a version that already exists, ..."""


class Progress:
    """What the writer reports to a progress bar (``core.console.progress_bar`` fits)."""

    def start(self, total: int) -> None: ...

    def advance(self, *_: Any) -> None: ...


@dataclass
class ReleaseReport:
    version: str
    path: str | None
    cards: int
    formats: list[str]
    min_grade: str
    date: str
    changes: dict[str, Any]
    grades: dict[str, int]
    excluded: list[dict[str, Any]]
    seconds: float
    files: int = 0
    bytes: int = 0
    dry_run: bool = False
    manifest_sha256: str | None = None
    release_id: int | None = None
    notes: str = ""
    views: dict[str, Any] | None = None  # with the views component: cards with views, and why the others have none
    leftovers_removed: list[dict[str, Any]] = field(default_factory=list)  # staging folders of killed exports
    stereo: dict[str, Any] | None = None  # with the stereo component: cards, cost per format per card, failures
    manifest: dict[str, dict[str, Any]] = field(default_factory=dict, repr=False)

    def as_json(self) -> dict[str, Any]:
        return {
            "version": self.version,
            "path": self.path,
            "cards": self.cards,
            "formats": self.formats,
            "min_grade": self.min_grade,
            "date": self.date,
            "changes": self.changes,
            "grades": self.grades,
            "excluded": self.excluded,
            "seconds": round(self.seconds, 3),
            "files": self.files,
            "bytes": self.bytes,
            "dry_run": self.dry_run,
            "manifest_sha256": self.manifest_sha256,
            "release_id": self.release_id,
            "cards_per_second": round(self.cards / self.seconds, 2) if self.seconds > 0 and not self.dry_run else None,
            "views": self.views,
            "leftovers_removed": self.leftovers_removed,
            "stereo": self.stereo,
        }


@dataclass(frozen=True)
class _Previous:
    version: str | None
    manifest: dict[str, dict[str, Any]] | None


def _previous() -> _Previous:
    row = latest_release()
    if row is None:
        return _Previous(None, None)
    return _Previous(row.version, dict((row.stats or {}).get("manifest") or {}))


def _count_grades(manifest: dict[str, dict[str, Any]]) -> dict[str, int]:
    counts = Counter(entry["grade"] for entry in manifest.values())
    return {grade: counts.get(grade, 0) for grade in ("few", "some")}


def plan_release(
    *, min_grade: str = "some", formats: str | tuple[str, ...] = DEFAULT_FORMATS, notes: str = "", data_dir: Path | None = None
) -> ReleaseReport:
    """The dry run: which cards would go in, what changed since the last release, the version.

    Reads the catalogue only (no file is written); cards whose outputs are incomplete are
    listed in ``excluded`` with the reason.
    """
    clock = time.perf_counter()
    fmt = parse_formats(formats)
    grades_at_or_above(min_grade)
    data_dir = data_dir or _data_dir()
    with read_only():
        ids = eligible_card_ids(min_grade)
        previous = _previous()
        date = inputs_date(ids)
        exclusions: list[Exclusion] = []
        manifest: dict[str, dict[str, Any]] = {}
        views = _ViewsCount() if "views" in fmt else None
        for card in stream_release_cards(ids, data_dir, exclusions, with_views=views is not None):
            manifest[str(card.card_id)] = card.manifest_entry()
            if views is not None:
                views.add(card.views_note or "views not run")
    changes = compare_manifests(previous.manifest, manifest, previous.version)
    return ReleaseReport(
        version=next_version(previous.version, changes.kind),
        path=None,
        cards=len(manifest),
        formats=list(fmt),
        min_grade=min_grade,
        date=date.isoformat(),
        changes=changes.as_json(),
        grades=_count_grades(manifest),
        excluded=[{"card_id": e.card_id, "reason": e.reason} for e in exclusions],
        seconds=time.perf_counter() - clock,
        dry_run=True,
        notes=notes,
        manifest=manifest,
        views=views.as_json() if views is not None else None,
    )


class _ViewsCount:
    """How many cards have views, and how many lack them for each reason."""

    def __init__(self) -> None:
        self.with_views = 0
        self.without: dict[str, int] = {}

    def add(self, note: str) -> None:
        if note == "done":
            self.with_views += 1
        else:
            self.without[note] = self.without.get(note, 0) + 1

    def as_json(self) -> dict[str, Any]:
        return {
            "cards_with_views": self.with_views,
            "cards_without_views": sum(self.without.values()),
            "without": dict(sorted(self.without.items())),
        }


def _data_dir() -> Path:
    from core.console import data_dir

    return data_dir()


def publish_release(
    out_dir: str | os.PathLike[str],
    *,
    min_grade: str = "some",
    formats: str | tuple[str, ...] = DEFAULT_FORMATS,
    notes: str = "",
    actor: Person | None = None,
    actor_label: str = "cli",
    progress: Progress | None = None,
    data_dir: Path | None = None,
) -> ReleaseReport:
    """Write a release of the accepted cards into ``<out_dir>/<version>``, record a Release row
    and an audit event. Raises :class:`ReleaseError` when there is nothing to release or the
    version's folder or row already exists; nothing is left behind on any error."""
    clock = time.perf_counter()
    fmt = parse_formats(formats)
    data_dir = data_dir or _data_dir()
    out = Path(out_dir).resolve()
    plan = plan_release(min_grade=min_grade, formats=fmt, notes=notes, data_dir=data_dir)
    if plan.cards == 0:
        raise ReleaseError(
            f"no curator-accepted cards at grade {' or '.join(grades_at_or_above(min_grade))} with finished "
            "rectification and disparity: review cards on /review (accept or change their grade) first"
            + (
                f"; {len(plan.excluded)} accepted card(s) excluded, e.g. card {plan.excluded[0]['card_id']}: "
                f"{plan.excluded[0]['reason']}"
                if plan.excluded
                else ""
            )
        )
    out.mkdir(parents=True, exist_ok=True)
    leftovers = remove_stale_partials(out)  # of exports killed before they could clean up
    holder = ReleaseStaging(out, plan.version)
    staging = holder.path
    try:
        report = _write(staging, plan, fmt, data_dir, progress)
        target = out / report.version
        if target.exists():
            raise ReleaseError(f"{target} already exists: releases are immutable; choose another --out")
        release = Release(
            version=report.version,
            path=str(target),
            min_grade=min_grade,
            formats=list(fmt),
            card_count=report.cards,
            notes=notes,
            manifest_sha256=report.manifest_sha256 or "",
            created_by=actor.id if actor is not None else None,
            stats={
                "grades": report.grades,
                "bytes": report.bytes,
                "files": report.files,
                "seconds": round(time.perf_counter() - clock, 3),
                "date": report.date,
                "excluded": report.excluded,
                "views": report.views,
                "manifest": report.manifest,
            },
            changes=report.changes,
        )
        db.session.add(release)
        try:
            db.session.flush()
        except IntegrityError as exc:
            db.session.rollback()
            raise ReleaseError(f"release {report.version} is already recorded in the catalogue") from exc
        from core.audit import record_event

        record_event(
            entity="release",
            action="publish",
            entity_id=release.id,
            actor=actor,
            actor_label=actor_label,
            after={
                "version": report.version,
                "cards": report.cards,
                "formats": list(fmt),
                "min_grade": min_grade,
                "manifest_sha256": report.manifest_sha256,
            },
            why=notes or f"release {report.version}",
        )
        make_world_readable(staging)
        os.replace(staging, target)
        try:
            db.session.commit()
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)
            raise
    except BaseException:
        db.session.rollback()
        shutil.rmtree(staging, ignore_errors=True)
        raise
    finally:
        holder.close()
    report.path, report.release_id = str(target), release.id
    report.leftovers_removed = [leftover.as_json() for leftover in leftovers]
    report.seconds = time.perf_counter() - clock
    return report


def _write(root: Path, plan: ReleaseReport, fmt: tuple[str, ...], data_dir: Path, progress: Progress | None) -> ReleaseReport:
    clock = time.perf_counter()
    date = datetime.fromisoformat(plan.date)
    ledger = FileLedger(root)
    scratch = root / ".scratch.exr"
    writers: list[Any] = []
    if "keystonedepth" in fmt:
        writers.append(KeystoneDepthWriter(ledger, scratch))
    if "parquet" in fmt:
        writers.append(ParquetWriter(ledger))
    if "webdataset" in fmt:
        writers.append(WebDatasetWriter(ledger, date.timestamp()))
    views_writer = ViewsWriter(ledger, scratch) if "views" in fmt else None
    if views_writer is not None:
        writers.append(views_writer)
    stereo_writer = StereoWriter(ledger) if "stereo" in fmt else None
    if stereo_writer is not None:
        writers.append(stereo_writer)
    if progress is not None:
        progress.start(plan.cards)
    manifest: dict[str, dict[str, Any]] = {}
    exclusions: list[Exclusion] = []
    crowd_answers = crowd_cards = 0
    with read_only(), open(root / "cards.jsonl", "wb") as cards_file:
        ids = [int(key) for key in sorted(plan.manifest, key=int)]
        plan.manifest = {}  # the ids are all that is needed from the plan: keep one manifest in memory
        for card in stream_release_cards(ids, data_dir, exclusions, with_views=views_writer is not None):
            try:
                payload = build_payload(card)
            except (OSError, ValueError) as exc:  # one bad card never stops a release
                exclusions.append(Exclusion(card.card_id, f"unreadable output: {exc}"))
                continue
            cards_file.write(payload.record_json + b"\n")
            for writer in writers:
                writer.add(payload)
            manifest[str(card.card_id)] = payload.card.manifest_entry()  # the card as written (views may be dropped)
            answers = sum(int(task.get("answers") or 0) for task in card.crowd.values())
            crowd_answers += answers
            crowd_cards += 1 if card.crowd else 0
            if progress is not None:
                progress.advance()
    for writer in writers:
        writer.close()
    ledger.record_file("cards.jsonl")
    if not manifest:
        raise ReleaseError(
            "every eligible card was excluded: " + "; ".join(f"card {e.card_id}: {e.reason}" for e in exclusions[:5])
        )

    previous = _previous_for(plan)
    changes = compare_manifests(previous.manifest, manifest, previous.version)
    version = next_version(previous.version, changes.kind)
    grades = _count_grades(manifest)
    excluded = plan.excluded + [{"card_id": e.card_id, "reason": e.reason} for e in exclusions]
    views: dict[str, Any] | None = None
    if views_writer is not None:
        views = {
            "cards_with_views": views_writer.with_views,
            "cards_without_views": sum(views_writer.without.values()),
            "without": dict(sorted(views_writer.without.items())),
        }
    stereo = stereo_writer.summary() if stereo_writer is not None else None
    ledger.write_bytes("CHANGELOG.md", changelog(version, plan.date, changes, excluded, views, stereo).encode())
    ledger.write_bytes(
        "README.md",
        dataset_card(version, plan.date, len(manifest), grades, fmt, plan.notes, changes, plan.min_grade, views, stereo).encode(),
    )
    crowd = {"answers_per_card": crowd_answers / crowd_cards if crowd_cards else None, "cards_with_crowd": crowd_cards}
    with open(root / "croissant.json", "wb") as handle:
        write_croissant(
            handle,
            ledger.files,
            version=version,
            date=plan.date,
            card_count=len(manifest),
            grade_counts=grades,
            crowd=crowd,
            notes=plan.notes,
            views_count=views["cards_with_views"] if views is not None else None,
            stereo_count=stereo["cards"] if stereo is not None else None,
        )
    ledger.record_file("croissant.json")
    sums_hash = hashlib.sha256()
    sums_bytes = 0
    with open(root / "SHA256SUMS", "wb") as handle:
        for path, (sha, _) in sorted(ledger.files.items()):
            line = f"{sha}  {path}\n".encode()
            handle.write(line)
            sums_hash.update(line)
            sums_bytes += len(line)
    return ReleaseReport(
        version=version,
        path=None,
        cards=len(manifest),
        formats=list(fmt),
        min_grade=plan.min_grade,
        date=plan.date,
        changes=changes.as_json(),
        grades=grades,
        excluded=excluded,
        seconds=time.perf_counter() - clock,
        files=len(ledger.files) + 1,
        bytes=ledger.total_bytes + sums_bytes,
        manifest_sha256=sums_hash.hexdigest(),
        notes=plan.notes,
        manifest=manifest,
        views=views,
        stereo=stereo,
    )


def _previous_for(plan: ReleaseReport) -> _Previous:
    with read_only():
        return _previous()


def changelog(
    version: str,
    date: str,
    changes: Changes,
    excluded: list[dict[str, Any]],
    views: dict[str, Any] | None = None,
    stereo: dict[str, Any] | None = None,
) -> str:
    """CHANGELOG.md: cards added, removed and changed against the previous release, and why;
    with the views component, how many cards have views and why the others have none."""
    day = date[:10]
    lines = ["# Changelog", "", f"## {version} ({day})", ""]
    if changes.previous_version is None:
        lines.append(f"First release: {len(changes.added)} card(s).")
    else:
        lines.append(
            f"Against {changes.previous_version}: a {changes.kind} release "
            f"({len(changes.added)} added, {len(changes.removed)} removed, {len(changes.changed)} changed)."
        )
    if changes.previous_version is not None:
        sections = (
            ("Added", [f"- card {key_of(i)}" for i in changes.added]),
            (
                "Removed",
                [f"- card {key_of(i)}: no longer accepted at this grade, or its outputs are incomplete" for i in changes.removed],
            ),
            ("Changed", [f"- card {key_of(i)}: " + "; ".join(why) for i, why in sorted(changes.changed.items())]),
        )
        for title, items in sections:
            lines += ["", f"### {title} ({len(items)})", ""] + (items or ["- none"])
    if views is not None:
        total = views["cards_with_views"] + views["cards_without_views"]
        lines += ["", f"### Views ({views['cards_with_views']} of {total} cards)", ""]
        lines.append(f"- {views['cards_with_views']} card(s) with the five GD images, cameras and preview under `views/`")
        lines += [f"- {count} card(s) without views: {reason}" for reason, count in views["without"].items()]
    if stereo is not None:
        total = stereo["cards"] + stereo["cards_without"]
        lines += ["", f"### Stereo files ({stereo['cards']} of {total} cards)", ""]
        lines.append(f"- {stereo['cards']} card(s) with an anaglyph, two wiggles, side-by-side, JPS and MPO under `stereo/`")
        lines += [f"- {count} card(s) without: {reason}" for reason, count in stereo["without"].items()]
    if excluded:
        lines += ["", f"### Accepted but not released ({len(excluded)})", ""]
        lines += [f"- card {key_of(e['card_id'])}: {e['reason']}" for e in excluded]
    return "\n".join(lines) + "\n"


def key_of(card_id: int) -> str:
    from .records import card_key

    return card_key(card_id)


def dataset_card(
    version: str,
    date: str,
    cards: int,
    grades: dict[str, int],
    fmt: tuple[str, ...],
    notes: str,
    changes: Changes,
    min_grade: str,
    views: dict[str, Any] | None = None,
    stereo: dict[str, Any] | None = None,
) -> str:
    """README.md in the Hugging Face dataset-card layout (YAML header, then the template's sections)."""
    size = "n<1K" if cards < 1000 else "1K<n<10K" if cards < 10_000 else "10K<n<100K"
    header = [
        "---",
        "pretty_name: Keystone stereographs",
        "license: other",
        "license_name: public-domain-mark-where-applicable",
        "task_categories:",
        "- depth-estimation",
        "tags:",
        "- stereo",
        "- disparity",
        "- cultural-heritage",
        "size_categories:",
        f"- {size}",
    ]
    if "parquet" in fmt:
        header += ["configs:", "- config_name: default", "  data_files:", "  - split: train", "    path: data/train-*.parquet"]
    header.append("---")
    layout = []
    if "keystonedepth" in fmt:
        layout += [
            "- `cropped/cropped_full_LR/<id>L.png`, `<id>R.png`: the left and right views cropped from the scan "
            "(KeystoneDepth's layout; loaders written for it work).",
            "- `processed/rectified/disp_info_LR/<id>L.exr`, `<id>R.exr`: float32 disparity of the left and right "
            "rectified views, channel `Y`, pixels; `x_right = x_left - d`; NaN = unknown.",
            "- `processed/rectified/rectified_LR/<id>L.png`, `<id>R.png`: the rectified pair.",
            "- `processed/rectified/rectification/<id>.json`: `H_l`, `H_r` (3 x 3, column vectors, `x' ~ H x`, "
            "cropped view -> rectified view), `K`, `R`, `t`, crop boxes `[x0, y0, x1, y1]` in card pixels.",
            "- `processed/depth_512/<id>.exr`: depth up to scale (focal_px * baseline / d, baseline 1), 512 x 512.",
            "- `original/<id>.<ext>`: the scan as ingested (never modified).",
        ]
    if "parquet" in fmt:
        layout.append(
            "- `data/train-*.parquet`: one row per card; image columns (`original`, `cropped_left/right`, "
            "`rectified_left/right`) load as images with `datasets.load_dataset('parquet', ...)` or "
            "`load_dataset(<this folder>)`; maps are `list<list<float32>>`; typed metadata columns."
        )
    if "webdataset" in fmt:
        layout.append(
            "- `webdataset/keystone-*.tar`: WebDataset shards; keys are the dot-free card ids, members "
            "`<id>.json`, `<id>.left.png`, `<id>.right.png`, `<id>.disparity_left.npy`, ..."
        )
    if views is not None:
        layout.append(
            f"- `views/<id>/`: the five GD images of the scene for {views['cards_with_views']} of "
            f"{views['cards_with_views'] + views['cards_without_views']} cards (the others have no finished views: "
            "graded failure, not run, or failed; `cards.jsonl` says why per card under `views`): `v0.png` (the "
            "reference view) and `v1.png`..`v4.png` (the four quad-corner views), 8-bit grey, or 8-bit RGB where "
            "the card's rectified view is in colour (`views.json` says `colour`); `v0_depth.exr`.."
            "`v4_depth.exr`, float32 channel `Y`, depth along each view's -z axis in baseline units (up to scale), "
            "finite and > 0 at every pixel (EXR as KeystoneDepth's maps); `views.json`, the five cameras (OpenGL "
            "convention, `x_cam = R x_world + t`, world = v0's camera, focal length in px, principal point at the "
            "image centre); `preview.webp`, an animated parallax preview. `views/views.jsonl` lists them."
        )
    if stereo is not None:
        layout.append(
            f"- `stereo/<id>/`: viewing files of the rectified pair for {stereo['cards']} cards: `anaglyph.jpg` "
            "(red-cyan, Dubois least-squares matrices, red filter on the left eye), `wiggle.gif` and `wiggle.webp` "
            "(a looping sweep from the left view to the right one and back, in-between views synthesised by warping "
            "the left view by a fraction of the disparity), `sbs_full.jpg` and `sbs_half.jpg` (parallel side-by-side: "
            "left view on the left; half = each view squeezed to half width, for 3D TVs and headsets), `cross.jps` "
            "(JPS: cross-eyed, right view on the left) and `pair.mpo` (multi-picture JPEG, left view first, for 3D "
            "displays and cameras). Each carries the card's title, date, accession and licence (EXIF and XMP; "
            "the GIF's comment). `stereo/stereo.jsonl` lists them."
        )
    layout += [
        "- `cards.jsonl`: one JSON record per card (museum metadata and URL, boxes, transforms, grade, review "
        "decision, pipeline versions and parameter hashes).",
        "- `croissant.json` (Croissant 1.1 with Responsible-AI fields), `SHA256SUMS`, `CHANGELOG.md`.",
        "",
        "Check a copy with `keystone verify <folder>` or `sha256sum -c SHA256SUMS`.",
    ]
    since = (
        "first release"
        if changes.previous_version is None
        else f"{changes.kind} release after {changes.previous_version}: {len(changes.added)} added, "
        f"{len(changes.removed)} removed, {len(changes.changed)} changed (see CHANGELOG.md)"
    )
    body = [
        "",
        f"# Keystone stereographs {version}",
        "",
        "## Dataset Description",
        "",
        f"Antique stereo cards turned into rectified stereo pairs with disparity and depth, after KeystoneDepth. "
        f"Release {version} of {date[:10]}: {cards} cards ({grades.get('few', 0)} with few artifacts, "
        f"{grades.get('some', 0)} with some artifacts; minimum grade `{min_grade}`); {since}.",
        *([""] + [f"Notes: {notes.strip()}"] if notes.strip() else []),
        "",
        "## Dataset Structure",
        "",
        *layout,
        "",
        "## Dataset Creation",
        "",
        "### Curation Rationale",
        "",
        "Historic stereographs hold real stereo geometry; recovering it gives depth data of the past.",
        "",
        "### Source Data",
        "",
        "Scans of stereo cards with the holding museum's catalogue records (accession number, title, date, "
        "creator, publisher, place, URL where known). Each card's metadata travels in `cards.jsonl`.",
        "",
        "## Annotations",
        "",
        "Crowd workers judged each card (a stereo pair? upside down? inverted?) and drew crop boxes on both halves; "
        "answers were aggregated and disputes went to curators. The automatic grader rated every rectified pair "
        "(few / some artifacts / failure); a curator accepted or changed each grade of this release. Annotator "
        "identities are not released.",
        "",
        "## Bias, Risks, and Limitations",
        "",
        "Commercial stereo publishers chose tourist sites, exhibitions and staged scenes; captions carry the views "
        "of their time. Cards graded failure are left out, so difficult scenes are under-represented. Depth is up "
        "to scale and estimated from optical flow, not measured; pairs are never perfectly rectified.",
        "",
        "## Citation",
        "",
        "```bibtex",
        "@inproceedings{luo2020keystonedepth,",
        "  title={KeystoneDepth: History in 3D},",
        "  author={Luo, Xuan and Kong, Yanmeng and Lawrence, Jason and Martin-Brualla, Ricardo and Seitz, Steven M.},",
        "  booktitle={International Conference on 3D Vision (3DV)},",
        "  year={2020}",
        "}",
        "```",
        "",
    ]
    return "\n".join(header + body)


__all__ = ["CardPayload", "ReleaseError", "ReleaseReport", "plan_release", "publish_release"]
