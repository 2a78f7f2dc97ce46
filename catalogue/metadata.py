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

Nothing is last-wins and one bad row never costs the file: a malformed record (unterminated
quote, a field over the csv module's size limit) is rejected by itself and parsing goes on
(:func:`read_csv_records`); rows that describe one accession number or file name differently are
all rejected (:func:`_reject_duplicate_keys` says why); a column given twice is reported and
not loaded (:func:`_unique_names`).
"""

from __future__ import annotations

import csv
import itertools
import re
from collections.abc import Iterator
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
    problems: list[str] = field(default_factory=list)  # about the file, not one row: a duplicated column, ...


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


@dataclass(frozen=True)
class CsvRecord:
    """One CSV record in file order: its cells, or why its line could not be parsed."""

    line: int  # 1-based physical line the record starts on
    cells: list[str] | None
    problem: str | None = None


def _read_lines(path: Path) -> list[str]:
    # newline="" keeps the line ends, so a quoted field's own newlines survive for the csv module;
    # iterating splits only on \n, \r and \r\n (never on the form feeds str.splitlines knows).
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            return list(handle)
    except UnicodeDecodeError:
        with path.open(newline="", encoding="latin-1") as handle:
            return list(handle)


class _RecordError(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _parse_record(lines: list[str], start: int) -> tuple[list[str], int]:
    """Parse one record beginning at ``lines[start]``; returns its cells and how many lines it used.

    Raises :class:`_RecordError` for a quote that never closes, text after a closing quote, or a
    field over ``csv.field_size_limit()``."""
    used = 0

    def feed() -> Iterator[str]:
        nonlocal used
        for line in itertools.islice(lines, start, None):
            used += 1
            yield line

    try:
        cells = next(csv.reader(feed(), strict=True))
    except csv.Error as exc:
        text = str(exc)
        if "field larger than field limit" in text:
            raise _RecordError(
                f"a field is longer than {csv.field_size_limit():,} characters (the CSV field size limit)"
            ) from exc
        if used > 1 or "unexpected end of data" in text:
            # The parser left this line inside a quoted field: the quote opened here never closes
            # where it should, and reading on would swallow the rows after it.
            raise _RecordError("a quoted field opened on this line never closes (unterminated quote)") from exc
        raise _RecordError(f"malformed CSV ({text}): a quote inside a field must be doubled") from exc
    return cells, used


def read_csv_records(path: Path) -> list[CsvRecord]:
    """Read a CSV record by record, so one malformed record costs only itself; blank lines are dropped.

    A record that cannot be parsed from its first line (an unterminated quote swallows the rest
    of the file; a field over the csv module's size limit) is reported by that line, and parsing
    starts again on the next line. A record spanning several lines is kept only when its field
    count is the first record's (the header's): a stray quote that merges good rows into one
    record is undone the same way, line by line, instead of silently eating them. (A stray quote
    whose merged record happens to have the header's field count cannot be told from a real
    multi-line field: it stays one record.)
    """
    lines = _read_lines(path)
    records: list[CsvRecord] = []
    width: int | None = None
    index = 0
    while index < len(lines):
        line_number = index + 1
        try:
            cells, used = _parse_record(lines, index)
        except _RecordError as exc:
            records.append(CsvRecord(line_number, None, exc.reason))
            index += 1
            continue
        if used > 1 and width is not None and len(cells) != width:
            records.append(
                CsvRecord(
                    line_number,
                    None,
                    (
                        f"a quoted field opened on this line runs over {used} lines and leaves {len(cells)} fields "
                        f"instead of {width}: probably an unterminated quote"
                    ),
                )
            )
            index += 1
            continue
        if any(cell.strip() for cell in cells):
            records.append(CsvRecord(line_number, cells))
            width = len(cells) if width is None else width
        index += used
    return records


def read_metadata(path: str | Path) -> MetadataFile:
    """Parse a metadata CSV. Malformed rows are listed in ``errors``; the rest is kept.

    Raises :class:`MetadataFormatError` when the file as a whole is unusable, and ``OSError``
    when it cannot be read.
    """
    path = Path(path)
    records = read_csv_records(path)
    good = [record for record in records if record.cells is not None]
    if not good:
        raise MetadataFormatError(
            "the file has no rows"
            + (f" that parse ({len(records)} malformed line(s); line {records[0].line}: {records[0].problem})" if records else "")
        )
    if records[0].cells is None:
        raise MetadataFormatError(f"the header (line {records[0].line}) is malformed: {records[0].problem}")
    table = [record.cells for record in good if record.cells is not None]

    first_column = {_norm(row[0]) for row in table if row}
    if "accession number" in first_column and _norm(table[0][0]) != "accession number":
        result = _transposed(path, records, labelled=True)
    elif (
        len(table) == len(EMUSEUM_ROW_ORDER)
        and len(table[1]) > 0
        and all(ACCESSION_PATTERN.match(cell.strip()) or not cell.strip() for cell in table[1])
        and any(ACCESSION_PATTERN.match(cell.strip()) for cell in table[1])
    ):
        result = _transposed(path, records, labelled=False)
    else:
        result = _tidy(path, records)
    _reject_duplicate_keys(result)
    return result


def _transposed(path: Path, records: list[CsvRecord], labelled: bool) -> MetadataFile:
    result = MetadataFile(path=path, layout="emuseum-transposed")
    for record in records:
        if record.cells is None:
            result.problems.append(
                f"line {record.line} is malformed ({record.problem}): the field on that line is missing from every record"
            )
    table = [record.cells for record in records if record.cells is not None]
    if labelled:
        names = [row[0].strip() or "emuseum_key" for row in table]
        values = [row[1:] for row in table]
        keep = _unique_names(names, "field", result)
        names = [name for name, kept in zip(names, keep) if kept]
        values = [row for row, kept in zip(values, keep) if kept]
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


def _unique_names(names: list[str], kind: str, result: MetadataFile) -> list[bool]:
    """Which columns (or transposed field rows) to keep: a name given twice is dropped, every copy.

    Taking either copy would silently pick one of two values; a key column given twice makes the
    whole file ambiguous (:class:`MetadataFormatError`)."""
    positions: dict[str, list[int]] = {}
    for index, name in enumerate(names):
        if name.strip():
            positions.setdefault(_norm(name), []).append(index)
    keep = [True] * len(names)
    for normalised, where in positions.items():
        if len(where) < 2:
            continue
        places = " and ".join(str(i + 1) for i in where)
        spelled = " / ".join(sorted({names[i].strip() for i in where}))
        if normalised in FILE_COLUMNS or normalised in ACCESSION_COLUMNS:
            raise MetadataFormatError(
                f"key {kind} {spelled!r} appears {len(where)} times ({kind}s {places}): "
                "cannot tell which one names each record; remove or rename the copies"
            )
        for i in where:
            keep[i] = False
        result.problems.append(
            f"{kind} {spelled!r} appears {len(where)} times ({kind}s {places}): none of its "
            "values is loaded; rename or remove the copies and ingest the file again"
        )
    return keep


def _tidy(path: Path, records: list[CsvRecord]) -> MetadataFile:
    assert records[0].cells is not None  # read_metadata rejects a malformed header
    header = [cell.strip() for cell in records[0].cells]
    normalised = [_norm(h) for h in header]
    has_key = any(n in FILE_COLUMNS or n in ACCESSION_COLUMNS for n in normalised)
    if not has_key:
        raise MetadataFormatError("no key column: expected one of " + ", ".join(FILE_COLUMNS + ("Accession Number",)))
    layout = "emuseum-tidy" if "accession number" in normalised else "plain"
    result = MetadataFile(path=path, layout=layout)
    keep = _unique_names(header, "column", result)
    for number, record in enumerate(records[1:], start=1):
        row = record.cells
        if row is None:
            result.errors.append((number, f"row {number} (line {record.line}): {record.problem}"))
            continue
        if len(row) != len(header):
            result.errors.append((number, f"row {number} has {len(row)} fields, the header has {len(header)}"))
            continue
        fields = {name: value for name, value, kept in zip(header, row, keep) if kept and (name or value)}
        _append(result, number, fields)
    return result


def _reject_duplicate_keys(result: MetadataFile) -> None:
    """Rows naming the same accession number or file name: conflicting rows are all rejected.

    Neither "first wins" nor "last wins": which of two different museum records belongs to a card
    cannot be told from the file, and the wrong record attached to a card would ship in a release
    as its provenance, which is worse than none until the file is fixed. Rows that repeat another
    word for word conflict with nothing: the first loads and each repeat is reported.
    """
    groups: dict[str, list[MetadataRow]] = {}
    for row in result.rows:
        if row.accession:
            groups.setdefault(f"accession {row.accession}", []).append(row)
        if row.file_name:
            groups.setdefault(f"file {row.file_name.lower()}", []).append(row)
    reasons: dict[int, str] = {}
    repeats: dict[int, str] = {}
    for label, rows in groups.items():
        if len(rows) < 2:
            continue
        first = rows[0]
        if all(row.fields == first.fields for row in rows[1:]):
            for row in rows[1:]:
                repeats.setdefault(
                    row.row_number,
                    f"row {row.row_number} repeats row {first.row_number} ({label}) word for word: the first is loaded",
                )
            continue
        numbers = ", ".join(str(row.row_number) for row in rows)
        for row in rows:
            reasons[row.row_number] = (
                f"rows {numbers} all describe {label} with different values: none of them "
                "is loaded (which one is right cannot be told); fix the file and ingest it again"
            )
    for number, reason in repeats.items():
        reasons.setdefault(number, reason)
    if not reasons:
        return
    result.rows = [row for row in result.rows if row.row_number not in reasons]
    result.errors = sorted(result.errors + list(reasons.items()))


def _append(result: MetadataFile, number: int, fields: dict[str, Any]) -> None:
    lowered = {_norm(k): str(v).strip() for k, v in fields.items()}
    accession = next((lowered[c] for c in ACCESSION_COLUMNS if lowered.get(c)), None)
    file_name = next((lowered[c] for c in FILE_COLUMNS if lowered.get(c)), None)
    if accession is None and file_name is None:
        result.errors.append((number, f"row {number} has neither a file name nor an accession number"))
        return
    if file_name is not None:
        file_name = Path(file_name).name
    result.rows.append(MetadataRow(row_number=number, accession=accession, file_name=file_name, fields=_canonical_fields(fields)))


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
