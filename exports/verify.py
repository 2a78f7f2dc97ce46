"""``keystone verify``: check a release folder against its own manifests. No database needed.

Checks, naming each problem with the path it concerns: every line of ``SHA256SUMS`` is
well-formed, its file exists and has that sha256; every file present is listed; ``croissant.json``
parses, conforms to Croissant 1.1, lists each file with the same sha256 as ``SHA256SUMS``, and
(when ``mlcroissant`` is installed) passes its validation; then every registered format checks
the files of its own it finds (:meth:`exports.formats.ReleaseFormat.verify`: e.g. every Parquet
shard has the release schema, every ``views/<key>/`` folder is complete and indexed, every MPO
has two frames). Last, from ``cards.jsonl``, that nothing released was stale
(:func:`check_released_cards`): each card's released results were computed from the inputs its
people's decisions gave at release time, and its acceptance was given exactly those results, after
they were computed.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from .croissant import CROISSANT_VERSION
from .formats import registered_formats

_SUM_LINE = re.compile(r"^([0-9a-f]{64})  (\S(?:.*\S)?)$")


@dataclass
class VerifyReport:
    path: str
    checked: int = 0
    problems: list[dict[str, str]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def problem(self, path: str, problem: str) -> None:
        self.problems.append({"path": path, "problem": problem})

    def as_json(self) -> dict[str, Any]:
        return {"ok": self.ok, "path": self.path, "checked": self.checked, "problems": self.problems}


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _present_files(root: Path) -> set[str]:
    found = set()
    for folder, _dirs, files in os.walk(root):
        for name in files:
            found.add((Path(folder) / name).relative_to(root).as_posix())
    return found


def verify_release(path: str | os.PathLike[str], *, validate_croissant: bool = True) -> VerifyReport:
    """Check the release at ``path``; the report lists every problem found (empty when sound)."""
    root = Path(path)
    report = VerifyReport(path=str(root))
    if not root.is_dir():
        report.problem(str(root), "not a folder")
        return report
    sums_file = root / "SHA256SUMS"
    listed: dict[str, str] = {}
    if not sums_file.is_file():
        report.problem("SHA256SUMS", "missing: cannot check any checksum")
    else:
        for number, line in enumerate(sums_file.read_text(errors="replace").splitlines(), start=1):
            match = _SUM_LINE.match(line)
            if match is None:
                report.problem("SHA256SUMS", f"line {number} is not '<sha256>  <path>': {line[:80]!r}")
                continue
            digest, relative = match.groups()
            if relative.startswith("/") or ".." in Path(relative).parts:
                report.problem(relative, "listed with an absolute or escaping path")
                continue
            listed[relative] = digest
    for relative, digest in sorted(listed.items()):
        target = root / relative
        report.checked += 1
        if not target.is_file():
            report.problem(relative, "listed in SHA256SUMS but missing")
        elif _sha256(target) != digest:
            report.problem(relative, "sha256 does not match SHA256SUMS (file changed or corrupted)")
    for relative in sorted(_present_files(root) - set(listed) - {"SHA256SUMS"}):
        report.problem(relative, "present but not listed in SHA256SUMS")
    _check_croissant(root, listed, report, validate_croissant)
    for fmt in registered_formats():
        fmt.verify(root, listed, report)
    if "cards.jsonl" in listed and (root / "cards.jsonl").is_file():
        check_released_cards(root / "cards.jsonl", report)
    return report


def check_released_cards(cards_file: Path, report: VerifyReport) -> None:
    """Check each card record's ``acceptance`` against its ``pipeline``: a released result whose
    inputs digest is not the one the card's decisions gave at release time is stale; an
    acceptance given other results (``accepted_results``) or decided before a result it covers
    was computed does not apply to what was released. Records without an ``acceptance`` (releases
    made before it was recorded) are not checked."""
    for number, line in enumerate(cards_file.read_bytes().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError:
            report.problem("cards.jsonl", f"line {number} is not JSON")
            continue
        if not isinstance(record, dict) or not isinstance(record.get("acceptance"), dict):
            continue
        key = str(record.get("key") or f"line {number}")
        pipeline = record.get("pipeline") if isinstance(record.get("pipeline"), dict) else {}
        acceptance = record["acceptance"]
        for stage, digest in sorted((acceptance.get("inputs_now") or {}).items()):
            released = (pipeline.get(stage) or {}).get("inputs_digest")
            if released is not None and released != digest:
                report.problem(
                    "cards.jsonl",
                    f"card {key}: its released {stage} was computed from other decisions than the card had at release "
                    f"(inputs {released}, decisions gave {digest}): a stale result was released",
                )
        given = acceptance.get("accepted_results")
        if isinstance(given, dict):
            for stage, accepted in sorted(given.items()):
                now = pipeline.get(stage) or {}
                if any(now.get(field) != accepted.get(field) for field in ("param_hash", "inputs_digest", "computed_at")):
                    report.problem(
                        "cards.jsonl",
                        f"card {key}: its acceptance was given another {stage} result (computed at "
                        f"{accepted.get('computed_at')}) than the one released (computed at {now.get('computed_at')})",
                    )
        decided = _moment(acceptance.get("decided_at"))
        if decided is not None:
            for stage in ("rectify", "disparity"):
                computed = _moment((pipeline.get(stage) or {}).get("computed_at"))
                if computed is not None and computed > decided:
                    report.problem(
                        "cards.jsonl",
                        f"card {key}: its acceptance ({acceptance.get('decided_at')}) predates its released {stage} "
                        f"result ({(pipeline.get(stage) or {}).get('computed_at')})",
                    )


def _moment(value: Any) -> datetime | None:
    if not isinstance(value, str):
        return None
    try:
        moment = datetime.fromisoformat(value)
    except ValueError:
        return None
    return moment if moment.tzinfo is not None else moment.replace(tzinfo=UTC)


def _check_croissant(root: Path, listed: dict[str, str], report: VerifyReport, validate: bool) -> None:
    target = root / "croissant.json"
    if not target.is_file():
        report.problem("croissant.json", "missing")
        return
    try:
        document = json.loads(target.read_text())
    except (UnicodeDecodeError, ValueError) as exc:
        report.problem("croissant.json", f"not valid JSON: {exc}")
        return
    if not isinstance(document, dict):
        report.problem("croissant.json", "not a JSON-LD object")
        return
    if document.get("conformsTo") != CROISSANT_VERSION:
        report.problem("croissant.json", f"conformsTo is {document.get('conformsTo')!r}, expected {CROISSANT_VERSION}")
    described = set()
    for entry in document.get("distribution") or []:
        if not isinstance(entry, dict) or entry.get("@type") != "cr:FileObject":
            continue
        relative = str(entry.get("contentUrl", ""))
        described.add(relative)
        if relative not in listed:
            report.problem("croissant.json", f"describes {relative!r}, which SHA256SUMS does not list")
        elif entry.get("sha256") != listed[relative]:
            report.problem("croissant.json", f"sha256 of {relative!r} differs from SHA256SUMS")
    for relative in sorted(set(listed) - described - {"croissant.json"}):
        report.problem("croissant.json", f"does not describe {relative!r}")
    if validate and not report.problems:
        try:
            import mlcroissant as mlc
        except ImportError:
            return
        try:
            # rdflib (under mlcroissant) warns about its own deprecated API; not ours to fix.
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                mlc.Dataset(str(target))
        except Exception as exc:  # mlcroissant raises ValidationError and, on odd input, anything
            report.problem("croissant.json", f"mlcroissant validation failed: {str(exc).strip()[:500]}")
