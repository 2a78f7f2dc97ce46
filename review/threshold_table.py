"""The grade's reasons as a table a curator can read: each measurement beside the threshold it
is closest to, the margin between them, which side of it the value lies, and the one
measurement nearest its threshold (the likeliest to flip the grade).

A grade record written by a grader that stores ``nearest`` (``{"measurement", "value",
"threshold", "margin", "level"}``) names the nearest measurement itself; older records hold
only the measurements, ``levels`` and a ``thresholds_hash``, and the table is computed here
from the thresholds that hash names (a fitted :class:`review.models.GradeModel`, or the
defaults). When no known thresholds match the hash, the active ones are used and the table
says so.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Any

from sqlalchemy import select

from core.db import db

from .models import GradeModel

LEVEL_WORDS = {0: "few artifacts", 1: "some artifacts", 2: "failure"}


@dataclass(frozen=True)
class ThresholdRow:
    measurement: str
    value: str  # formatted in the measurement's unit
    threshold: str  # the threshold nearest the value, with its comparison ("< 80 %")
    threshold_level: str  # which grade the threshold starts ("some artifacts", "failure")
    margin: str  # value minus threshold, in the unit, signed
    side: str  # "within" (the good side of that threshold) or "beyond"
    level: str  # the level this measurement reached
    distance: float  # log-ratio distance on the measurement's own scale (inf for flags)


@dataclass(frozen=True)
class ThresholdTable:
    rows: list[ThresholdRow]
    nearest: ThresholdRow | None
    thresholds_known: bool  # False: compared with the active thresholds, not the grade's own
    from_record: bool  # the grade record named its nearest measurement itself


def _thresholds_for(metrics: dict[str, Any]) -> tuple[Any, bool]:
    """The thresholds the grade was computed with (by ``thresholds_hash``), else the active ones."""
    from pipeline.errors import InvalidInputError
    from pipeline.grading import GradeThresholds
    from pipeline.records import param_hash

    from .grading import active_grade_params

    wanted = metrics.get("thresholds_hash")
    candidates = [GradeThresholds()]
    for model in db.session.scalars(select(GradeModel).order_by(GradeModel.id.desc())):
        with contextlib.suppress(InvalidInputError):  # a row another version wrote: not these thresholds
            candidates.append(GradeThresholds.from_dict(model.thresholds))
    for candidate in candidates:
        if wanted and param_hash(candidate) == wanted:
            return candidate, True
    return active_grade_params()[0].thresholds, False


def _number(value: Any) -> float | None:
    if isinstance(value, bool):
        return 1.0 if value else 0.0
    if isinstance(value, (int, float)) and math.isfinite(value):
        return float(value)
    return None


def _show(value: float, unit: str) -> str:
    """A value in its unit as a curator reads it (fractions as percent)."""
    if unit in ("percent", "percent1"):
        return f"{100 * value:.{2 if unit == 'percent1' else 1}f} %"
    if unit in ("px", "deg"):
        return f"{value:.1f} {unit}"
    return f"{value:.3g}"


def _show_limit(limit: float, unit: str) -> str:
    """Thresholds as short as they are exact: 80 %, 1.5 px, 0.5 %."""
    if unit in ("percent", "percent1"):
        return f"{100 * limit:.6g} %"
    if unit in ("px", "deg"):
        return f"{limit:.6g} {unit}"
    return f"{limit:.6g}"


def _show_margin(margin: float, unit: str) -> str:
    if unit in ("percent", "percent1"):
        return f"{100 * margin:+.2f} points"
    if unit in ("px", "deg"):
        return f"{margin:+.1f} {unit}" if round(margin, 1) else f"{margin:+.3f} {unit}"
    return f"{margin:+.3g}"


def _row(check: dict[str, Any]) -> ThresholdRow | None:
    """One row from a grade check: ``{"measurement", "value", "unit", "direction", "some",
    "failure", "level", "margin", "distance"}`` (margin and distance to the nearer threshold)."""
    name, unit, direction = check.get("measurement"), check.get("unit"), check.get("direction")
    value = _number(check.get("value"))
    if not isinstance(name, str) or value is None or direction not in ("above", "below"):
        return None
    level = str(check.get("level") or "?")
    level_words = {"few": LEVEL_WORDS[0], "some": LEVEL_WORDS[1], "failure": LEVEL_WORDS[2]}.get(level, level)
    if unit == "flag":
        beyond = level != "few"
        return ThresholdRow(
            name,
            "yes" if value >= 0.5 else "no",
            "set or not",
            LEVEL_WORDS[1],
            "—",
            "beyond" if beyond else "within",
            level_words,
            math.inf,
        )
    margin = _number(check.get("margin"))
    limits = [
        (limit, lv) for limit, lv in ((_number(check.get("some")), 1), (_number(check.get("failure")), 2)) if limit is not None
    ]
    if margin is None or not limits:
        return None
    # The threshold the margin was measured to: value - margin, matched to the nearer of the two.
    limit, limit_level = min(limits, key=lambda pair: abs((value - margin) - pair[0]))
    beyond = value > limit if direction == "above" else value < limit
    distance = _number(check.get("distance"))
    return ThresholdRow(
        name,
        _show(value, str(unit)),
        f"{'>' if direction == 'above' else '<'} {_show_limit(limit, str(unit))}",
        LEVEL_WORDS[limit_level],
        _show_margin(margin, str(unit)),
        "beyond" if beyond else "within",
        level_words,
        math.inf if distance is None else distance,
    )


def threshold_table(metrics: dict[str, Any] | None) -> ThresholdTable | None:
    """The table for a grade record's ``metrics``; None when it holds no per-measurement levels.

    Records from the current grader carry ``checks`` (one row per measurement) and ``nearest``;
    for older ones the measurements are graded again (:func:`pipeline.grading.grade`, pure and
    fast) against the thresholds the record's ``thresholds_hash`` names, to get the same rows.
    """
    metrics = metrics or {}
    nested = metrics.get("measurements")
    measurements: dict[str, Any] = nested if isinstance(nested, dict) else metrics
    checks, nearest_entry, known, from_record = metrics.get("checks"), metrics.get("nearest"), True, True
    if not isinstance(checks, list) or not checks:
        levels = metrics.get("levels")
        if not isinstance(levels, dict) or not levels:
            return None
        from pipeline.errors import PipelineError
        from pipeline.grading import grade

        thresholds, known = _thresholds_for(metrics)
        values = {name: measurements.get(name) for name in levels}
        try:
            result = grade(values, thresholds)
        except PipelineError:
            return None
        recorded = isinstance(nearest_entry, dict)  # a grader that named its nearest but kept no checks
        checks, nearest_entry, from_record = result.checks, nearest_entry if recorded else result.nearest, recorded
    rows = [row for row in (_row(check) for check in checks if isinstance(check, dict)) if row is not None]
    rows.sort(key=lambda row: row.distance)
    wanted = nearest_entry.get("measurement") if isinstance(nearest_entry, dict) else None
    nearest = next((row for row in rows if row.measurement == wanted), None)
    if nearest is None:
        finite = [row for row in rows if math.isfinite(row.distance)]
        nearest, from_record = (finite[0] if finite else None), False
    return ThresholdTable(rows, nearest, known, from_record)
