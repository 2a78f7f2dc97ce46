"""Read museum metadata CSVs into catalogue records keyed by accession number or file name.

Formats understood (detected from the file itself):

* eMuseum export, tidy: one row per record, a column ``Accession Number`` (the Keystone-Mast
  scrape in ``keystone_mast_records.csv``).
* eMuseum export, transposed: one *column* per record, the field names in the first column
  (``photo_infos_1370.csv``), or, as in the scraper's small sample, no field-name column at
  all but the scraper's fixed row order (``EMUSEUM_ROW_ORDER``).
* A plain CSV with a header and a key column: ``file_name`` / ``filename`` / ``file`` /
  ``image`` and/or ``accession`` / ``accession_number``.

Every column is kept, known or not; a few are also copied to canonical keys (``accession``,
``title``, ``date``, ...) so the rest of the tool can rely on them.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ACCESSION_PATTERN = re.compile(r"^\d{4}\.\d{4}\.[\w.-]+$")

# Field order of the KeystoneDepth eMuseum scraper (AnnyKong/Web-Crawler) when it writes no
# field-name column: the record key, then the fields in alphabetical order.
EMUSEUM_ROW_ORDER = (
    "emuseum_key",
    "Accession Number",
    "Creator",
    "Credit Line",
    "Date",
    "Description",
    "Inscriptions",
    "Medium",
    "Place Depicted",
    "Publisher",
    "Subjects",
    "Title",
)

FILE_COLUMNS = ("file_name", "filename", "file", "image", "image_file", "source")
ACCESSION_COLUMNS = ("accession", "accession_number", "accession number", "accession no", "accession no.")
CANONICAL = {
    "title": ("title",),
    "date": ("date",),
    "creator": ("creator", "photographer"),
    "publisher": ("publisher",),
    "place": ("place depicted", "place"),
    "subjects": ("subjects", "subject"),
    "description": ("description",),
    "medium": ("medium",),
    "url": ("url", "museum_url", "link"),
    "credit_line": ("credit line", "credit_line"),
    "emuseum_key": ("emuseum_key",),
}


class MetadataFormatError(ValueError):
    """The file as a whole cannot be read as metadata (no header, no key column, not CSV)."""


@dataclass(frozen=True)
class MetadataRow:
    row_number: int  # 1-based data row (tidy) or record column (transposed) in the file
    accession: str | None
    file_name: str | None
    fields: dict[str, Any]

    @property
    def record_key(self) -> str:
        if self.accession:
            return f"accession:{self.accession}"
        assert self.file_name is not None
        return f"file:{self.file_name.lower()}"


@dataclass
class MetadataFile:
    path: Path
    layout: str  # "emuseum-tidy" | "emuseum-transposed" | "plain"
    rows: list[MetadataRow] = field(default_factory=list)
    errors: list[tuple[int, str]] = field(default_factory=list)  # (row number, reason)


def _norm(name: str) -> str:
    return " ".join(name.strip().lower().replace("\ufeff", "").split())


def _canonical_fields(fields: dict[str, Any]) -> dict[str, Any]:
    lowered = {_norm(k): v for k, v in fields.items()}
    out = dict(fields)
    for key, names in CANONICAL.items():
        for name in names:
            value = lowered.get(name)
            if value not in (None, ""):
                out.setdefault(key, value)
                break
    return out


def _read_table(path: Path) -> list[list[str]]:
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            return list(csv.reader(handle, strict=True))
    except UnicodeDecodeError:
        with path.open(newline="", encoding="latin-1") as handle:
            return list(csv.reader(handle, strict=True))


def read_metadata(path: str | Path) -> MetadataFile:
    """Parse a metadata CSV. Malformed rows are listed in ``errors``; the rest is kept.

    Raises :class:`MetadataFormatError` when the file as a whole is unusable, and ``OSError``
    when it cannot be read.
    """
    path = Path(path)
    try:
        table = _read_table(path)
    except csv.Error as exc:
        raise MetadataFormatError(f"not a readable CSV: {exc}") from exc
    table = [row for row in table if any(cell.strip() for cell in row)]
    if not table:
        raise MetadataFormatError("the file has no rows")

    first_column = {_norm(row[0]) for row in table if row}
    if "accession number" in first_column and _norm(table[0][0]) != "accession number":
        return _transposed(path, table, labelled=True)
    if len(table) == len(EMUSEUM_ROW_ORDER) and len(table[1]) > 0 and all(
        ACCESSION_PATTERN.match(cell.strip()) or not cell.strip() for cell in table[1]
    ) and any(ACCESSION_PATTERN.match(cell.strip()) for cell in table[1]):
        return _transposed(path, table, labelled=False)
    return _tidy(path, table)


def _transposed(path: Path, table: list[list[str]], labelled: bool) -> MetadataFile:
    result = MetadataFile(path=path, layout="emuseum-transposed")
    if labelled:
        names = [row[0].strip() or "emuseum_key" for row in table]
        values = [row[1:] for row in table]
    else:
        names = list(EMUSEUM_ROW_ORDER)
        values = table
    width = max(len(row) for row in values)
    for column in range(width):
        fields: dict[str, Any] = {}
        for name, row in zip(names, values):
            cell = row[column] if column < len(row) else ""
            if name == "(not assigned)" and not cell:
                continue
            fields[name] = cell
        if "emuseum_key" not in fields and not labelled:
            fields["emuseum_key"] = values[0][column] if column < len(values[0]) else ""
        _append(result, column + 1, fields)
    return result


def _tidy(path: Path, table: list[list[str]]) -> MetadataFile:
    header = [cell.strip() for cell in table[0]]
    normalised = [_norm(h) for h in header]
    has_key = any(n in FILE_COLUMNS or n in ACCESSION_COLUMNS for n in normalised)
    if not has_key:
        raise MetadataFormatError(
            "no key column: expected one of " + ", ".join(FILE_COLUMNS + ("Accession Number",))
        )
    layout = "emuseum-tidy" if "accession number" in normalised else "plain"
    result = MetadataFile(path=path, layout=layout)
    for number, row in enumerate(table[1:], start=1):
        if len(row) != len(header):
            result.errors.append((number, f"row {number} has {len(row)} fields, the header has {len(header)}"))
            continue
        fields = {name: value for name, value in zip(header, row) if name or value}
        _append(result, number, fields)
    return result


def _append(result: MetadataFile, number: int, fields: dict[str, Any]) -> None:
    lowered = {_norm(k): str(v).strip() for k, v in fields.items()}
    accession = next((lowered[c] for c in ACCESSION_COLUMNS if lowered.get(c)), None)
    file_name = next((lowered[c] for c in FILE_COLUMNS if lowered.get(c)), None)
    if accession is None and file_name is None:
        result.errors.append((number, f"row {number} has neither a file name nor an accession number"))
        return
    if file_name is not None:
        file_name = Path(file_name).name
    result.rows.append(
        MetadataRow(row_number=number, accession=accession, file_name=file_name, fields=_canonical_fields(fields))
    )


def card_keys(source_name: str) -> list[str]:
    """Record keys a card with this file name answers to: its name, its stem, its stem as accession."""
    name = Path(source_name).name
    stem = Path(name).stem
    return [f"file:{name.lower()}", f"file:{stem.lower()}", f"accession:{stem}"]


def row_keys(row: MetadataRow) -> list[str]:
    keys = []
    if row.accession:
        keys.append(f"accession:{row.accession}")
    if row.file_name:
        keys.append(f"file:{row.file_name.lower()}")
        keys.append(f"file:{Path(row.file_name).stem.lower()}")
    return keys
