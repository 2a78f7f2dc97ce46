"""What killed commands leave behind, cleared when the next one starts.

``keystone run`` removes, at its start, the temporary files a killed ingest left in the store
and the staging folders of killed exports in the web's releases folder; each card's work folder
(views, stage artifacts) is cleared of a killed run's ``.tmp`` files just before the card runs
again (:func:`pipeline.runner.clear_stale_temp_files`: only cards in flight when a run died can
hold them, and a walk of the whole ``derived`` tree costs tens of seconds at 500,000 files).
``keystone export`` clears its own ``--out`` folder (:func:`exports.staging.remove_stale_partials`).
The driver sits below the exports feature and does not import it: the app factory registers that
function here (:func:`register_staging_cleaner`) and the run calls what is registered.
A running command's files are never touched: temporary files only once unchanged for
:data:`~pipeline.io.STALE_TEMP_SECONDS`, staging folders only when their export's lock is free.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from pipeline.io import STALE_TEMP_SECONDS, remove_stale_temp_files

if TYPE_CHECKING:
    from flask import Flask

TEMP_FOLDERS = ("originals",)  # under the data dir; "derived" is cleared card by card by the runner
STAGING_CLEANERS_KEY = "keystone.staging_cleaners"


class RemovedFolder(Protocol):
    """What a staging cleaner reports for each folder it removed."""

    @property
    def path(self) -> str: ...

    @property
    def bytes(self) -> int: ...


# Removes the staging folders of dead writers in a folder; returns what it removed.
StagingCleaner = Callable[[Path], Iterable[RemovedFolder]]


def register_staging_cleaner(app: Flask, cleaner: StagingCleaner) -> None:
    """Have ``keystone run`` clear, at its start, what ``cleaner`` judges dead in the releases folder."""
    app.extensions.setdefault(STAGING_CLEANERS_KEY, []).append(cleaner)


@dataclass
class LeftoversReport:
    temp_files: int = 0
    staging_folders: int = 0
    bytes: int = 0
    paths: list[str] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        return {"temp_files": self.temp_files, "staging_folders": self.staging_folders, "bytes": self.bytes, "paths": self.paths}


def remove_leftovers(
    data_dir: Path,
    releases_dir: Path | None = None,
    *,
    staging_cleaners: Iterable[StagingCleaner] = (),
    stale_temp_seconds: float = STALE_TEMP_SECONDS,
) -> LeftoversReport:
    """Remove stale temporary files in the originals store and, with each of ``staging_cleaners``,
    dead exports' staging folders in ``releases_dir`` (default ``<data dir>/releases``)."""
    report = LeftoversReport()
    for name in TEMP_FOLDERS:
        for path, size in remove_stale_temp_files(data_dir / name, stale_temp_seconds):
            report.temp_files += 1
            report.bytes += size
            report.paths.append(str(path))
    for cleaner in staging_cleaners:
        for leftover in cleaner(releases_dir or data_dir / "releases"):
            report.staging_folders += 1
            report.bytes += leftover.bytes
            report.paths.append(leftover.path)
    return report


def clear_leftovers(as_json: bool) -> LeftoversReport:
    """:func:`remove_leftovers` for the app's data dir and releases folder, saying what went
    (on stderr under ``--json``, so stdout stays one JSON document)."""
    from flask import current_app

    from core.console import data_dir, say

    configured = current_app.config.get("KEYSTONE_RELEASES_DIR")
    cleaners = current_app.extensions.get(STAGING_CLEANERS_KEY, [])
    report = remove_leftovers(data_dir(), Path(configured) if configured else None, staging_cleaners=cleaners)
    if report.paths:
        say(
            f"removed {report.temp_files} temporary file(s) and {report.staging_folders} export staging folder(s) "
            f"({report.bytes / 1e6:.1f} MB) left by interrupted commands",
            as_json,
        )
    return report
