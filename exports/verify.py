"""``keystone verify``: check a release folder against its own manifests. No database needed.

Checks, naming each problem with the path it concerns: every line of ``SHA256SUMS`` is
well-formed, its file exists and has that sha256; every file present is listed; ``croissant.json``
parses, conforms to Croissant 1.1, lists each file with the same sha256 as ``SHA256SUMS``, and
(when ``mlcroissant`` is installed) passes its validation; every Parquet shard has the release
schema, and the shards and ``cards.jsonl`` hold the same number of cards; every ``views/<key>/``
folder holds all twelve files of a card's views and ``views/views.jsonl`` lists exactly those cards;
every ``stereo/<key>/`` folder holds the seven stereo files, ``stereo/stereo.jsonl`` lists exactly
those cards, each MPO opens with two frames of one size and each JPS is an even-width image.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .croissant import CROISSANT_VERSION

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
    _check_parquet(root, listed, report)
    _check_views(root, listed, report)
    _check_stereo(root, listed, report)
    return report


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


def _check_parquet(root: Path, listed: dict[str, str], report: VerifyReport) -> None:
    shards = sorted(p for p in listed if p.startswith("data/") and p.endswith(".parquet"))
    if not shards:
        return
    import pyarrow.parquet as pq

    from .writers import parquet_schema

    expected = parquet_schema()
    rows = 0
    for relative in shards:
        try:
            schema = pq.read_schema(root / relative)
            rows += pq.ParquetFile(root / relative).metadata.num_rows
        except Exception as exc:  # pyarrow raises several error types for a damaged file
            report.problem(relative, f"not a readable Parquet file: {exc}")
            continue
        if not schema.equals(expected, check_metadata=False):
            report.problem(relative, "Parquet schema differs from the release schema")
        elif (schema.metadata or {}).get(b"huggingface") != expected.metadata[b"huggingface"]:
            report.problem(relative, "Parquet 'huggingface' features entry missing or different")
    cards_file = root / "cards.jsonl"
    if cards_file.is_file():
        with open(cards_file, "rb") as handle:
            cards = sum(1 for line in handle if line.strip())
        if cards != rows:
            report.problem("data/", f"Parquet shards hold {rows} cards, cards.jsonl {cards}")


def _check_views(root: Path, listed: dict[str, str], report: VerifyReport) -> None:
    from .writers import VIEWS_INDEX, view_files

    folders: dict[str, set[str]] = {}
    for relative in listed:
        parts = relative.split("/")
        if len(parts) == 3 and parts[0] == "views":
            folders.setdefault(parts[1], set()).add(relative)
    if not folders and VIEWS_INDEX not in listed:
        return
    for key, present in sorted(folders.items()):
        missing = sorted(set(view_files(key)) - present)
        extra = sorted(present - set(view_files(key)))
        if missing:
            report.problem(f"views/{key}/", f"incomplete views: {', '.join(p.rsplit('/', 1)[1] for p in missing)} not listed")
        if extra:
            report.problem(f"views/{key}/", f"unexpected files: {', '.join(p.rsplit('/', 1)[1] for p in extra)}")
    index = root / VIEWS_INDEX
    if VIEWS_INDEX not in listed or not index.is_file():
        report.problem(VIEWS_INDEX, "missing: views folders are present but not indexed")
        return
    try:
        keys = [json.loads(line)["key"] for line in index.read_text().splitlines() if line.strip()]
    except (UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        report.problem(VIEWS_INDEX, f"not one JSON record with a key per line: {exc}")
        return
    if sorted(keys) != sorted(folders):
        report.problem(VIEWS_INDEX, f"lists {len(keys)} card(s) with views, the release has {len(folders)} views folder(s)")


def _check_stereo(root: Path, listed: dict[str, str], report: VerifyReport) -> None:
    from .stereo import STEREO_INDEX, stereo_files

    folders: dict[str, set[str]] = {}
    for relative in listed:
        parts = relative.split("/")
        if len(parts) == 3 and parts[0] == "stereo":
            folders.setdefault(parts[1], set()).add(relative)
    if not folders and STEREO_INDEX not in listed:
        return
    for key, present in sorted(folders.items()):
        expected = set(stereo_files(key))
        missing, extra = sorted(expected - present), sorted(present - expected)
        if missing:
            report.problem(f"stereo/{key}/", f"incomplete: {', '.join(p.rsplit('/', 1)[1] for p in missing)} not listed")
        if extra:
            report.problem(f"stereo/{key}/", f"unexpected files: {', '.join(p.rsplit('/', 1)[1] for p in extra)}")
        for relative in sorted(present & expected):
            if relative.endswith((".mpo", ".jps")) and (root / relative).is_file():
                _check_stereo_image(root / relative, relative, report)
    index = root / STEREO_INDEX
    if STEREO_INDEX not in listed or not index.is_file():
        report.problem(STEREO_INDEX, "missing: stereo folders are present but not indexed")
        return
    try:
        keys = [json.loads(line)["key"] for line in index.read_text().splitlines() if line.strip()]
    except (UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        report.problem(STEREO_INDEX, f"not one JSON record with a key per line: {exc}")
        return
    if sorted(keys) != sorted(folders):
        report.problem(STEREO_INDEX, f"lists {len(keys)} card(s), the release has {len(folders)} stereo folder(s)")


def _check_stereo_image(path: Path, relative: str, report: VerifyReport) -> None:
    """An MPO must hold two frames of one size; a JPS must be an even-width image."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            if relative.endswith(".mpo"):
                frames = getattr(image, "n_frames", 1)
                if image.format != "MPO" or frames != 2:
                    report.problem(relative, f"expected an MPO with 2 frames, got {image.format} with {frames}")
                    return
                size = image.size
                image.seek(1)
                if image.size != size:
                    report.problem(relative, f"the MPO's frames differ in size: {size} and {image.size}")
            elif image.width % 2:
                report.problem(relative, f"a JPS holds two views side by side: odd width {image.width}")
    except (OSError, UnidentifiedImageError, SyntaxError) as exc:
        report.problem(relative, f"not a readable image: {exc}")
