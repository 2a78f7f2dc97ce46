"""Ingest: copy scans into the content-addressed store and register them as cards.

The store lives under ``KEYSTONE_DATA_DIR/originals/<hash[:2]>/<sha256><ext>``; files are
written through a temporary name and renamed, then made read-only, so an original is never
half-written and never modified. Each card is committed on its own, so an interrupted ingest
loses at most the file in flight: running the same command again skips what is stored
(duplicates by content hash are a no-op that says so) and carries on.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from flask import current_app
from flask.cli import with_appcontext
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from catalogue.iiif import is_iiif_source
from catalogue.metadata import MetadataFormatError, MetadataRow, card_keys, read_metadata, row_keys
from catalogue.originals import (
    card_with_hash,
    database_reason,
    discard_original,
    duplicate_entry,
    sha256_regular_file,
    store_original,
)
from core.db import db
from core.models import Card, Collection, MetadataRecord
from pipeline.errors import ImageReadError
from pipeline.io import IMAGE_SUFFIXES, probe_image
from pipeline.split import MIN_HEIGHT, MIN_WIDTH

if TYPE_CHECKING:
    from catalogue.iiif_ingest import FetchOptions
    from catalogue.stereo_ingest import StereoOptions

DEFAULT_COLLECTION = "default"


@dataclass
class IngestReport:
    ingested: list[dict[str, Any]] = field(default_factory=list)
    duplicates: list[dict[str, Any]] = field(default_factory=list)
    rejected: list[dict[str, str]] = field(default_factory=list)
    metadata: dict[str, int] = field(default_factory=lambda: {"rows": 0, "matched": 0, "unmatched": 0})

    def as_json(self) -> dict[str, Any]:
        return {
            "ingested": len(self.ingested),
            "duplicates": len(self.duplicates),
            "rejected": self.rejected,
            "cards": self.ingested,
            "duplicate_files": self.duplicates,
            "metadata": self.metadata,
        }


def _os_reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def discover_files(paths: Iterable[str | Path], report: IngestReport) -> Iterator[Path]:
    """Yield image files under ``paths`` (recursively, sorted), rejecting unusable paths.

    A file named explicitly with an unsupported extension is rejected; inside folders such
    files (a README, a metadata CSV) are passed over silently. A folder that cannot be listed
    (no permission) is rejected with its reason, never skipped in silence; the rest goes on.
    """
    for raw in paths:
        path = Path(raw)
        try:
            mode: int | None = path.lstat().st_mode
        except FileNotFoundError:
            report.rejected.append({"path": str(path), "reason": "no such file or folder"})
            continue
        except OSError as exc:  # e.g. a path inside a folder we may not enter
            report.rejected.append({"path": str(path), "reason": f"cannot look at it: {_os_reason(exc)}"})
            continue
        if mode is not None and stat.S_ISLNK(mode):
            try:
                mode = path.stat().st_mode  # a link named on the command line is followed
            except OSError:
                mode = None  # broken: the file check below says so
        if mode is not None and stat.S_ISDIR(mode):
            yield from _walk_folder(path, report)
        elif path.suffix.lower() not in IMAGE_SUFFIXES:
            report.rejected.append(
                {
                    "path": str(path),
                    "reason": f"unsupported file type {path.suffix or '(none)'!r}; expected one of "
                    + ", ".join(sorted(IMAGE_SUFFIXES)),
                }
            )
        else:
            yield path


def _walk_folder(root: Path, report: IngestReport) -> list[Path]:
    """Image files under ``root``, sorted; folders that cannot be listed are rejected by name.

    Links to folders are not followed inside a folder (a link back up would loop); each is
    reported so nothing under it is skipped unseen."""
    found: list[Path] = []
    pending = [root]
    while pending:
        folder = pending.pop()
        try:
            with os.scandir(folder) as listing:
                entries = list(listing)
        except OSError as exc:
            report.rejected.append(
                {"path": str(folder), "reason": f"cannot list folder: {_os_reason(exc)}; nothing under it was ingested"}
            )
            continue
        for entry in entries:
            child = Path(entry.path)
            try:
                is_folder = entry.is_dir(follow_symlinks=False)
                linked_folder = not is_folder and entry.is_symlink() and entry.is_dir()
            except OSError:
                is_folder = linked_folder = False
            if is_folder:
                pending.append(child)
            elif linked_folder:
                report.rejected.append(
                    {
                        "path": str(child),
                        "reason": "a symbolic link to a folder: links are not "
                        "followed inside folders; name it on the command line to ingest it",
                    }
                )
            elif child.suffix.lower() in IMAGE_SUFFIXES:
                found.append(child)
    return sorted(found)


def get_or_create_collection(name: str) -> Collection:
    collection = db.session.scalar(select(Collection).where(Collection.name == name))
    if collection is None:
        collection = Collection(name=name)
        db.session.add(collection)
        db.session.flush()
    return collection


def _store_metadata_rows(collection_id: int, source: Path, rows: list[MetadataRow]) -> list[int]:
    """Upsert rows by record key (a later CSV refines an earlier one); returns their ids."""
    ids = []
    existing = {
        record.record_key: record
        for record in db.session.scalars(select(MetadataRecord).where(MetadataRecord.collection_id == collection_id))
    }
    for row in rows:
        record = existing.get(row.record_key)
        if record is None:
            record = MetadataRecord(collection_id=collection_id, record_key=row.record_key)
            db.session.add(record)
            existing[row.record_key] = record
        record.accession = row.accession
        record.file_name = row.file_name
        record.fields = row.fields
        record.source_file = str(source)
        record.row_number = row.row_number
        db.session.flush()
        ids.append(record.id)
    return ids


def _apply_metadata(card: Card, record: MetadataRecord) -> None:
    record.card_id = card.id
    card.source_metadata = {**(card.source_metadata or {}), **record.fields}
    if record.accession:
        card.accession = record.accession


def _link_metadata(collection_id: int) -> None:
    """Attach unlinked metadata records of the collection to the cards they name."""
    unlinked = list(
        db.session.scalars(
            select(MetadataRecord).where(MetadataRecord.collection_id == collection_id, MetadataRecord.card_id.is_(None))
        )
    )
    if not unlinked:
        return
    by_key: dict[str, Card] = {}
    for card in db.session.scalars(select(Card).where(Card.collection_id == collection_id)):
        for key in card_keys(card.source_name):
            by_key.setdefault(key, card)
    for record in unlinked:
        row = MetadataRow(record.row_number, record.accession, record.file_name, record.fields)
        card = next((by_key[k] for k in row_keys(row) if k in by_key), None)
        if card is not None:
            _apply_metadata(card, record)


def ingest(
    paths: Iterable[str | Path],
    *,
    data_dir: Path,
    collection_name: str = DEFAULT_COLLECTION,
    metadata_csv: Path | None = None,
    max_pixels: int,
    on_start: Callable[[int], None] | None = None,
    on_file: Callable[[Any], None] | None = None,
    stereo: StereoOptions | None = None,
    fetch: FetchOptions | None = None,
) -> IngestReport:
    """Ingest files and folders, IIIF manifests and collections (URLs or ``.json`` files, see
    :mod:`catalogue.iiif_ingest`) and a metadata CSV: every problem is a ``rejected`` entry with
    its reason and the rest goes on; a database that refuses writes (a full disk) rejects each
    file it touches, and no original stays in the store without its card."""
    report = IngestReport()
    try:
        collection = get_or_create_collection(collection_name)
        collection_id = collection.id
        db.session.commit()
    except SQLAlchemyError as exc:
        db.session.rollback()
        report.rejected.append(
            {
                "path": _database_label(),
                "reason": f"cannot write the catalogue database ({database_reason(exc)}): nothing was ingested",
            }
        )
        return report

    metadata_ids: list[int] = []
    if metadata_csv is not None:
        metadata_ids = _ingest_metadata(collection_id, metadata_csv, report)

    paths = list(paths)
    iiif_sources = [str(raw) for raw in paths if is_iiif_source(raw)]
    canvases: list[Any] = []
    if iiif_sources:
        from catalogue.iiif_ingest import FetchOptions as _FetchOptions, IiifClient, gather_canvases

        client = IiifClient(fetch or _FetchOptions())
        canvases = gather_canvases(iiif_sources, client, report)
    files = list(discover_files([raw for raw in paths if not is_iiif_source(raw)], report))
    # ---- stereo hook: MPOs, left/right pairs and JPS / side-by-side eye order (catalogue.stereo_ingest)
    # become cards there; the other files go on to the one-file-per-card ingest below.
    from catalogue.stereo_ingest import StereoOptions as _StereoOptions, ingest_stereo_inputs

    files = ingest_stereo_inputs(files, stereo or _StereoOptions(), collection_id, data_dir, max_pixels, report)
    # ---- end of the stereo hook
    if on_start is not None:
        on_start(len(canvases) + len(files))
    if canvases:
        from catalogue.iiif_ingest import ingest_canvases

        try:
            ingest_canvases(
                canvases,
                client,
                collection_id=collection_id,
                data_dir=data_dir,
                max_pixels=max_pixels,
                report=report,
                on_canvas=on_file,
            )
        finally:
            client.close()
    elif iiif_sources:
        client.close()
    for path in files:
        _ingest_one(path, collection_id, data_dir, max_pixels, report)
        if on_file is not None:
            on_file(path)

    try:
        _link_metadata(collection_id)
        db.session.commit()
        records = (
            db.session.scalars(select(MetadataRecord).where(MetadataRecord.id.in_(metadata_ids))).all() if metadata_ids else []
        )
    except SQLAlchemyError as exc:
        db.session.rollback()
        if metadata_csv is not None:
            report.rejected.append(
                {
                    "path": str(metadata_csv),
                    "reason": "metadata not attached to the new cards: "
                    f"the catalogue database refused the write ({database_reason(exc)}); "
                    "ingest the CSV again",
                }
            )
        return report
    if metadata_ids:
        report.metadata["matched"] = sum(1 for r in records if r.card_id is not None)
        unmatched = sorted((r for r in records if r.card_id is None), key=lambda r: r.row_number)
        report.metadata["unmatched"] = len(unmatched)
        for record in unmatched:
            label = f"accession {record.accession}" if record.accession else f"file {record.file_name}"
            report.rejected.append(
                {
                    "path": f"{metadata_csv}:{record.row_number}",
                    "reason": f"metadata row {record.row_number} ({label}) matches no ingested image; "
                    "the row is kept and will attach when the image is ingested",
                }
            )
    return report


def _database_label() -> str:
    return db.engine.url.render_as_string(hide_password=True)


def _ingest_metadata(collection_id: int, metadata_csv: Path, report: IngestReport) -> list[int]:
    try:
        parsed = read_metadata(metadata_csv)
    except (OSError, MetadataFormatError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        report.rejected.append({"path": str(metadata_csv), "reason": f"cannot read metadata: {reason}"})
        return []
    for problem in parsed.problems:
        report.rejected.append({"path": str(metadata_csv), "reason": f"metadata: {problem}"})
    for number, reason in parsed.errors:
        report.rejected.append({"path": f"{metadata_csv}:{number}", "reason": f"malformed metadata row: {reason}"})
    report.metadata["rows"] = len(parsed.rows)
    try:
        ids = _store_metadata_rows(collection_id, metadata_csv, parsed.rows)
        db.session.commit()
    except SQLAlchemyError as exc:
        db.session.rollback()
        report.rejected.append(
            {
                "path": str(metadata_csv),
                "reason": f"metadata not recorded: the catalogue "
                f"database refused the write ({database_reason(exc)}); none of its "
                f"{len(parsed.rows)} rows was stored",
            }
        )
        report.metadata["rows"] = 0
        return []
    return ids


def _ingest_one(path: Path, collection_id: int, data_dir: Path, max_pixels: int, report: IngestReport) -> None:
    try:
        content_hash = sha256_regular_file(path)
    except ImageReadError as exc:
        report.rejected.append({"path": str(path), "reason": str(exc)})
        return
    except OSError as exc:
        report.rejected.append({"path": str(path), "reason": f"unreadable: {_os_reason(exc)}"})
        return

    try:
        existing = db.session.scalar(select(Card).where(Card.content_hash == content_hash))
    except SQLAlchemyError as exc:
        db.session.rollback()
        report.rejected.append(
            {"path": str(path), "reason": f"not ingested: the catalogue database cannot be read ({database_reason(exc)})"}
        )
        return
    if existing is not None:
        report.duplicates.append(duplicate_entry(path, existing))
        return
    try:
        info = probe_image(path, max_pixels=max_pixels)
        if info.width < MIN_WIDTH or info.height < MIN_HEIGHT:
            # the filter refuses it at once: say so at the door rather than after a run
            raise ImageReadError(
                f"too small to be a stereo card: {info.width}x{info.height} px "
                f"(the smallest card the pipeline splits is {MIN_WIDTH}x{MIN_HEIGHT} px)"
            )
        relative = store_original(path, content_hash, data_dir)
    except ImageReadError as exc:
        report.rejected.append({"path": str(path), "reason": str(exc)})
        return
    except OSError as exc:
        report.rejected.append({"path": str(path), "reason": f"cannot store: {_os_reason(exc)}"})
        return

    card = Card(
        collection_id=collection_id,
        content_hash=content_hash,
        stored_path=str(relative),
        source_name=path.name,
        source_path=str(path.resolve()),
        width=info.width,
        height=info.height,
        image_format=info.format,
        byte_size=info.byte_size,
        source_metadata={},
    )
    try:
        db.session.add(card)
        db.session.flush()
        for record in db.session.scalars(
            select(MetadataRecord).where(
                MetadataRecord.collection_id == collection_id,
                MetadataRecord.record_key.in_(card_keys(card.source_name)),
            )
        ):
            _apply_metadata(card, record)
        db.session.commit()
    except SQLAlchemyError as exc:
        db.session.rollback()
        # Another ingest may have stored the same bytes between our check and our commit
        # (IntegrityError): then its card owns the original. Otherwise (a full disk, a lost
        # server) no card points at the file, so it goes: the store never keeps an orphan.
        existing = card_with_hash(content_hash)
        if existing is not None:
            report.duplicates.append(duplicate_entry(path, existing))
            return
        removed = discard_original(data_dir / relative)
        report.rejected.append(
            {
                "path": str(path),
                "reason": "not recorded: the catalogue database refused the "
                f"write ({database_reason(exc)}); "
                + ("the stored copy was removed" if removed else f"the stored copy {relative} could not be removed"),
            }
        )
        return
    report.ingested.append({"id": card.id, "path": str(path), "content_hash": content_hash})


@click.command("ingest")
# readable=False: click would end the whole command (exit 2) on one unreadable path; ingest
# rejects that path alone, with its reason, and goes on with the others.
# path_type=str: a URL stays a URL (pathlib would fold its "//").
@click.argument("paths", nargs=-1, type=click.Path(path_type=str, readable=False))
@click.option(
    "--metadata",
    "metadata_csv",
    type=click.Path(path_type=Path, readable=False),
    help="Museum metadata CSV (eMuseum export, tidy or transposed, or a plain CSV keyed by file_name or accession).",
)
@click.option(
    "--collection",
    "collection_name",
    default=DEFAULT_COLLECTION,
    show_default=True,
    help="Collection the cards belong to (created if new).",
)
@click.option(
    "--pairs",
    "pairs_csv",
    type=click.Path(path_type=Path),
    help="CSV with 'left' and 'right' columns: each row's two files become one card.",
)
@click.option(
    "--sbs-order",
    type=click.Choice(["cross", "parallel"]),
    help="Eye order of side-by-side files: cross (right view on the left) or parallel. "
    "JPS files default to cross; giving it treats every plain file as side by side.",
)
@click.option(
    "--timeout",
    "timeout_s",
    type=click.FloatRange(min=0.1),
    default=30.0,
    show_default=True,
    help="IIIF: seconds to wait for a server to answer (each request; failed ones are tried twice more).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the report as one JSON document.")
@with_appcontext
def ingest_command(
    paths: tuple[str, ...],
    metadata_csv: Path | None,
    collection_name: str,
    pairs_csv: Path | None,
    sbs_order: str | None,
    timeout_s: float,
    as_json: bool,
) -> None:
    """Copy scans (files or folders, recursively: jpg, png, tif, jps, mpo) into the catalogue.

    A PATH may also be a IIIF Presentation 3 or 2.1 manifest or collection, as an http(s) URL or
    a .json file: each canvas's image is fetched through its Image API service (the largest size
    the service and KEYSTONE_MAX_PIXELS allow) and becomes a card with the manifest's catalogue
    record; the canvas id stays on the card, so a rerun fetches no canvas twice.

    An MPO's two frames, and a left/right pair (named <stem>_L/_R, <stem>L/R, -left/-right, or
    listed in --pairs), each become one card; JPS files are read as cross-eyed unless
    --sbs-order says otherwise. Originals are stored as they came.

    Duplicates by content are a no-op; rerunning an interrupted ingest carries on where it
    stopped. Exits 1 when any file or metadata row was rejected (each is listed with a reason).
    """
    from catalogue.iiif_ingest import FetchOptions as _FetchOptions
    from catalogue.stereo_ingest import StereoOptions as _StereoOptions
    from core.console import data_dir, emit_json, ensure_database, progress_bar, say

    if not paths and metadata_csv is None and pairs_csv is None:
        raise click.UsageError("give at least one PATH, --pairs CSV or --metadata CSV")
    ensure_database()
    with progress_bar("ingest", enabled=not as_json) as progress:
        report = ingest(
            paths,
            data_dir=data_dir(),
            collection_name=collection_name,
            metadata_csv=metadata_csv,
            max_pixels=int(current_app.config["KEYSTONE_MAX_PIXELS"]),
            on_start=progress.start,
            on_file=progress.advance,
            stereo=_StereoOptions(pairs_csv=pairs_csv, sbs_order=sbs_order),
            fetch=_FetchOptions(timeout_s=timeout_s),
        )
    if as_json:
        emit_json(report.as_json())
    else:
        say(f"ingested {len(report.ingested)}, duplicates {len(report.duplicates)}, rejected {len(report.rejected)}", as_json)
        for entry in report.duplicates:
            say(f"  duplicate  {entry['path']}: {entry['reason']}", as_json)
        for entry in report.rejected:
            say(f"  rejected   {entry['path']}: {entry['reason']}", as_json)
        if metadata_csv is not None:
            meta = report.metadata
            say(f"metadata rows {meta['rows']}: matched {meta['matched']}, unmatched {meta['unmatched']}", as_json)
    if report.rejected:
        raise SystemExit(1)
