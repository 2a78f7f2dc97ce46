"""The report page's two charts as geometry for its inline SVG and table: drawn by the browser,
not by matplotlib.

The page showed two matplotlib PNGs; the first one a server process drew took 1.7-2.1 s (importing
matplotlib and its fonts), so the page took 2.2 s to show on first load. The same figures as SVG
rectangles cost nothing to draw; the PNGs stay at ``/reports/<name>.png`` for download.
"""

from __future__ import annotations

from typing import Any

from .models import GRADES
from .report import PAPER_DISTRIBUTION, PAPER_SAMPLE

MIN_LABELLED_WIDTH = 0.06  # a segment narrower than this fraction has no percentage written in it
SHADES = 5  # the confusion table's cells are shaded in this many steps (CSS classes shade-0..4)


def grade_bars(report: dict[str, Any]) -> list[dict[str, Any]]:
    """One stacked bar per series (the paper's, then each collection's automatic and curated
    grades where it has any): its label and its segments as ``x`` and ``width`` in 0..1 of the
    bar, with the grade and the percentage to write in it (``None`` when too narrow)."""
    series: list[tuple[str, dict[str, float | None]]] = [(f"paper ({PAPER_SAMPLE} cards)", dict(PAPER_DISTRIBUTION))]
    for entry in report["collections"]:
        for kind in ("automatic", "curated"):
            if any(entry[kind]["counts"].values()):
                series.append((f"{entry['collection']}: {kind}", entry[kind]["fractions"]))
    bars = []
    for label, fractions in series:
        left, segments = 0.0, []
        for grade in GRADES:
            width = float(fractions.get(grade) or 0.0)
            if width > 0:
                text = f"{width:.0%}" if width >= MIN_LABELLED_WIDTH else None
                segments.append({"grade": grade, "x": round(left, 4), "width": round(width, 4), "text": text})
            left += width
        bars.append({"label": label, "segments": segments})
    return bars


def confusion_shades(confusion: list[list[int]]) -> list[list[int]]:
    """Each cell's shade step 0..SHADES-1, by its count against the largest count."""
    largest = max((value for row in confusion for value in row), default=0)
    if largest == 0:
        return [[0 for _ in row] for row in confusion]
    return [[min(SHADES - 1, round((SHADES - 1) * value / largest)) for value in row] for row in confusion]
