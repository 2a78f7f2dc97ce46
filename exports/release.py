"""Publishing a release: plan (what goes in, what changed, which version), write, move into place.

A release is written into ``<out>/.<version>.partial-XXXX`` (locked while this export runs, see
:mod:`exports.staging`) and renamed to ``<out>/<version>``, world-readable, only when every file,
the Croissant metadata and ``SHA256SUMS`` are complete; any error removes the partial folder and
records nothing, and the folders of exports killed outright are removed by the next export. The same inputs give byte-identical files:
the release's date is the newest review decision among its cards, not the clock.

Publishing into one folder is one at a time (:class:`exports.staging.PublishLock`, held from the
plan to the record): a second publish meanwhile is refused, and one that starts after another
finished plans from the release it recorded, so a caller's ``check`` of the plan (the web's
"exactly what was previewed") sees that release. A kill between moving a release into place and
committing its row leaves a marker; the next publish into the folder removes that unrecorded
release rather than adopt it: it was never served (the pages serve recorded releases only), and
the next publish writes the same content again from the catalogue, byte for byte, under a version
planned from what the catalogue does record.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import select
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
from .formats import (
    ReleaseFormat,
    WriteContext,
    chosen_formats,
    default_format_names,
    format_encodings,
    parse_formats,
    registered_formats,
)
from .models import Release
from .records import Changes, compare_manifests, grades_at_or_above, next_version
from .release_words import release_summary
from .staging import (
    Leftover,
    PublishBusy,
    PublishLock,
    ReleaseStaging,
    clear_unrecorded,
    make_world_readable,
    publishing_markers,
    remove_stale_partials,
    write_publishing_marker,
)
from .writers import CardPayload, FileLedger, build_payload

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
    leftovers_removed: list[dict[str, Any]] = field(default_factory=list)  # staging folders of killed exports
    # Format name -> its writer's summary (the dry run: its plan tally), e.g. views: cards with views
    # and why the others have none; stereo: cards, cost per file kind per card, failures.
    summaries: dict[str, dict[str, Any]] = field(default_factory=dict)
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
            "leftovers_removed": self.leftovers_removed,
            # Each reporting format under its name (None when not in this release); a test holds
            # their names apart from the keys above.
            **{fmt.name: self.summaries.get(fmt.name) for fmt in registered_formats() if fmt.reports},
        }


@dataclass(frozen=True)
class _Previous:
    version: str | None
    manifest: dict[str, dict[str, Any]] | None
    formats: tuple[str, ...] = ()
    min_grade: str | None = None


def _previous() -> _Previous:
    row = latest_release()
    if row is None:
        return _Previous(None, None)
    return _Previous(row.version, dict((row.stats or {}).get("manifest") or {}), tuple(row.formats or ()), row.min_grade)


def _count_grades(manifest: dict[str, dict[str, Any]]) -> dict[str, int]:
    counts = Counter(entry["grade"] for entry in manifest.values())
    return {grade: counts.get(grade, 0) for grade in ("few", "some")}


def plan_release(
    *, min_grade: str = "some", formats: str | tuple[str, ...] | None = None, notes: str = "", data_dir: Path | None = None
) -> ReleaseReport:
    """The dry run: which cards would go in, what changed since the last release, the version.

    Reads the catalogue only (no file is written); cards whose outputs are incomplete are
    listed in ``excluded`` with the reason. ``formats``: names (default: the default formats).
    """
    clock = time.perf_counter()
    chosen = chosen_formats(default_format_names() if formats is None else formats)
    grades_at_or_above(min_grade)
    data_dir = data_dir or _data_dir()
    with read_only():
        ids = eligible_card_ids(min_grade)
        previous = _previous()
        date = inputs_date(ids)
        exclusions: list[Exclusion] = []
        manifest: dict[str, dict[str, Any]] = {}
        tallies = {fmt.name: tally for fmt in chosen if (tally := fmt.plan_tally()) is not None}
        for card in stream_release_cards(ids, data_dir, exclusions, with_views=_with_views(chosen)):
            manifest[str(card.card_id)] = card.manifest_entry()
            for tally in tallies.values():
                tally.add(card)
    changes = compare_manifests(previous.manifest, manifest, previous.version)
    return ReleaseReport(
        version=next_version(previous.version, changes.kind),
        path=None,
        cards=len(manifest),
        formats=[fmt.name for fmt in chosen],
        min_grade=min_grade,
        date=date.isoformat(),
        changes=changes.as_json(),
        grades=_count_grades(manifest),
        excluded=[{"card_id": e.card_id, "reason": e.reason} for e in exclusions],
        seconds=time.perf_counter() - clock,
        dry_run=True,
        notes=notes,
        manifest=manifest,
        summaries={name: tally.as_json() for name, tally in tallies.items()},
    )


def _with_views(chosen: Sequence[ReleaseFormat]) -> bool:
    """Whether the cards are read with their views artifacts (their manifest entries then carry
    the views digest): only when a chosen format releases them."""
    return any(fmt.with_views for fmt in chosen)


def _data_dir() -> Path:
    from core.console import data_dir

    return data_dir()


def publish_release(
    out_dir: str | os.PathLike[str],
    *,
    min_grade: str = "some",
    formats: str | tuple[str, ...] | None = None,
    notes: str = "",
    actor: Person | None = None,
    actor_label: str = "cli",
    progress: Progress | None = None,
    data_dir: Path | None = None,
    check: Callable[[ReleaseReport], None] | None = None,
) -> ReleaseReport:
    """Write a release of the accepted cards into ``<out_dir>/<version>``, record a Release row
    and an audit event. Raises :class:`ReleaseError` when there is nothing to release, another
    publish into ``out_dir`` is under way, or the version's folder or row already exists; nothing
    is left behind on any error. ``check(plan)``: called with the plan under the publish lock,
    before anything is written; it raises to refuse."""
    fmt = parse_formats(default_format_names() if formats is None else formats)
    out = Path(out_dir).resolve()
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)  # the lock is on the folder itself
    try:
        lock = PublishLock(out)
    except PublishBusy as exc:
        raise ReleaseError(str(exc)) from None
    try:
        return _publish_locked(out, min_grade, fmt, notes, actor, actor_label, progress, data_dir or _data_dir(), check)
    except BaseException:
        if made and not any(out.iterdir()):
            out.rmdir()  # a refused first publish leaves no empty folder behind
        raise
    finally:
        lock.close()


def _clear_unrecorded(out: Path) -> list[Leftover]:
    """Under the publish lock: each marker a dead publish left names a release it may have moved
    into place; recorded (the commit went through), only the marker goes, else the folder too."""
    cleared = []
    for version, marker in publishing_markers(out):
        with read_only():
            recorded = db.session.scalar(select(Release.id).where(Release.version == version, Release.path == str(out / version)))
        if recorded is not None:
            marker.unlink(missing_ok=True)
        elif (leftover := clear_unrecorded(out, version, marker)) is not None:
            cleared.append(leftover)
    return cleared


def _pause_for_tests(point: str) -> None:
    """``KEYSTONE_TEST_PAUSE=<point>:<file>``: create ``file`` and sleep at ``point``, so a test can
    kill the publish exactly there. Unset in real use."""
    wanted = os.environ.get("KEYSTONE_TEST_PAUSE", "")
    name, _, signal_file = wanted.partition(":")
    if name == point and signal_file:
        Path(signal_file).write_text(str(os.getpid()))
        time.sleep(600)


def _publish_locked(
    out: Path,
    min_grade: str,
    fmt: tuple[str, ...],
    notes: str,
    actor: Person | None,
    actor_label: str,
    progress: Progress | None,
    data_dir: Path,
    check: Callable[[ReleaseReport], None] | None,
) -> ReleaseReport:
    clock = time.perf_counter()
    unrecorded = _clear_unrecorded(out)
    plan = plan_release(min_grade=min_grade, formats=fmt, notes=notes, data_dir=data_dir)
    if check is not None:
        check(plan)
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
    leftovers = unrecorded + remove_stale_partials(out)  # of exports killed before they could clean up
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
                "summaries": report.summaries,  # format name -> its writer's summary
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
        marker = write_publishing_marker(out, report.version)
        os.replace(staging, target)
        _pause_for_tests("after-move")
        try:
            db.session.commit()
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)
            marker.unlink(missing_ok=True)
            raise
        marker.unlink(missing_ok=True)
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
    chosen = chosen_formats(fmt)
    context = WriteContext(ledger=ledger, scratch=root / ".scratch.exr", date=date)
    writers = [(chosen_format, chosen_format.writer(context)) for chosen_format in chosen]
    if progress is not None:
        progress.start(plan.cards)
    manifest: dict[str, dict[str, Any]] = {}
    exclusions: list[Exclusion] = []
    crowd_answers = crowd_cards = 0
    rights: Counter[str] = Counter()  # the museums' rights statements, carried into croissant.json and README.md
    with read_only(), open(root / "cards.jsonl", "wb") as cards_file:
        ids = [int(key) for key in sorted(plan.manifest, key=int)]
        plan.manifest = {}  # the ids are all that is needed from the plan: keep one manifest in memory
        for card in stream_release_cards(ids, data_dir, exclusions, with_views=_with_views(chosen)):
            try:
                payload = build_payload(card)
            except (OSError, ValueError) as exc:  # one bad card never stops a release
                exclusions.append(Exclusion(card.card_id, f"unreadable output: {exc}"))
                continue
            cards_file.write(payload.record_json + b"\n")
            statement = card.metadata.get("rights")
            if isinstance(statement, str) and statement:
                rights[statement] += 1
            for _, writer in writers:
                writer.add(payload)
            manifest[str(card.card_id)] = payload.card.manifest_entry()  # the card as written (views may be dropped)
            answers = sum(int(task.get("answers") or 0) for task in card.crowd.values())
            crowd_answers += answers
            crowd_cards += 1 if card.crowd else 0
            if progress is not None:
                progress.advance()
    for _, writer in writers:
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
    summaries = {written.name: summary for written, writer in writers if (summary := writer.summary()) is not None}
    sections = [line for written in chosen for line in written.changelog(summaries.get(written.name))]
    # In words, as the releases pages say it: "Format-only release: adds webdataset; same cards as 1.0.0".
    summary = release_summary(changes.as_json(), list(fmt), list(previous.formats), plan.min_grade, previous.min_grade)
    ledger.write_bytes("CHANGELOG.md", changelog(version, plan.date, changes, excluded, sections, summary).encode())
    ledger.write_bytes(
        "README.md",
        dataset_card(
            version, plan.date, len(manifest), grades, chosen, summaries, plan.notes, changes, plan.min_grade, dict(rights)
        ).encode(),
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
            record_sets=[
                record_set for written in chosen for record_set in written.record_sets(summaries.get(written.name), len(manifest))
            ],
            encodings=format_encodings(),
            rights=dict(rights),
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
        summaries=summaries,
    )


def _previous_for(plan: ReleaseReport) -> _Previous:
    with read_only():
        return _previous()


def changelog(
    version: str,
    date: str,
    changes: Changes,
    excluded: list[dict[str, Any]],
    format_sections: Sequence[str] = (),
    summary: str | None = None,
) -> str:
    """CHANGELOG.md: cards added, removed and changed against the previous release, and why, with
    ``summary`` (:func:`exports.release_words.release_summary`, e.g. a format-only release) under
    the counts; then the formats' own sections (``format_sections``, lines; e.g. how many cards
    have views and why the others have none), then the accepted cards left out."""
    day = date[:10]
    lines = ["# Changelog", "", f"## {version} ({day})", ""]
    if changes.previous_version is None:
        lines.append(f"First release: {len(changes.added)} card(s).")
    else:
        lines.append(
            f"Against {changes.previous_version}: a {changes.kind} release "
            f"({len(changes.added)} added, {len(changes.removed)} removed, {len(changes.changed)} changed)."
        )
        if summary:
            lines += ["", summary]
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
    lines += format_sections
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
    formats: Sequence[ReleaseFormat],
    summaries: dict[str, dict[str, Any]],
    notes: str,
    changes: Changes,
    min_grade: str,
    rights: dict[str, int] | None = None,
) -> str:
    """README.md in the Hugging Face dataset-card layout (YAML header, then the template's sections);
    each format adds its header lines and its items of "Dataset Structure"."""
    size = "n<1K" if cards < 1000 else "1K<n<10K" if cards < 10_000 else "10K<n<100K"
    rights = rights or {}
    header = [
        "---",
        "pretty_name: Keystone stereographs",
        "license: other",
        "license_name: " + ("museum-rights-statements" if rights else "public-domain-mark-where-applicable"),
        *([f"license_link: {next(iter(rights))}"] if len(rights) == 1 and sum(rights.values()) == cards else []),
        "task_categories:",
        "- depth-estimation",
        "tags:",
        "- stereo",
        "- disparity",
        "- cultural-heritage",
        "size_categories:",
        f"- {size}",
    ]
    for fmt in formats:
        header += fmt.readme_header()
    header.append("---")
    layout = [line for fmt in formats for line in fmt.readme_layout(summaries.get(fmt.name))]
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
        *_rights_lines(rights, cards),
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


def _rights_lines(rights: dict[str, int], cards: int) -> list[str]:
    """The museums' rights statements as they gave them, with how many cards each covers."""
    if not rights:
        return []
    lines = [
        "",
        "### Rights",
        "",
        "Each card keeps its holder's rights statement unchanged (`metadata.rights` in `cards.jsonl`):",
        "",
    ]
    lines += [f"- {statement}: {count} card(s)" for statement, count in sorted(rights.items())]
    without = cards - sum(rights.values())
    if without:
        lines.append(f"- no statement from the holder ({without} card(s)): public domain mark where applicable")
    return lines


__all__ = ["CardPayload", "ReleaseError", "ReleaseReport", "plan_release", "publish_release"]
