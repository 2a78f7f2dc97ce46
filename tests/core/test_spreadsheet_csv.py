"""CSV files for people: cells a spreadsheet would evaluate are written as text (OWASP's rule)."""

from __future__ import annotations

import csv
import io

import pytest

from core.spreadsheet_csv import spreadsheet_cell, write_spreadsheet_csv


@pytest.mark.parametrize(
    "value",
    ["=1+1", "+1", "-1+2", "@SUM(A1)", "\t=1", "\r=1", '=HYPERLINK("http://x","y")', "  =1+1", "-"],
)
def test_formula_like_text_gets_a_leading_quote(value):
    assert spreadsheet_cell(value) == "'" + value


@pytest.mark.parametrize("value", ["", "prolific:=x", "a=b", '{"swapped": false}', "2026-11-27T10:00:00", "'quoted", "x-1"])
def test_other_text_is_unchanged(value):
    assert spreadsheet_cell(value) == value


@pytest.mark.parametrize("value", [-3, -0.5, 0, True, False, None])
def test_numbers_and_other_values_are_unchanged(value):
    assert spreadsheet_cell(value) is value


def test_write_spreadsheet_csv_writes_every_cell_through_it():
    buffer = io.StringIO()
    write_spreadsheet_csv(buffer, ["id", "session"], [{"id": -1, "session": "=2*3"}, {"id": 2, "session": 'a,"b"\nc'}])
    rows = list(csv.DictReader(io.StringIO(buffer.getvalue())))
    assert rows == [{"id": "-1", "session": "'=2*3"}, {"id": "2", "session": 'a,"b"\nc'}]
