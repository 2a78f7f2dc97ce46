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

from app.db import db

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


def _row(name: str, value: float, level: int, threshold: Any) -> ThresholdRow | None:
    from pipeline.grading import _RULES, _distance, _format, _threshold_text

    rule = _RULES.get(name)
    if rule is None:
        return None
    if rule.unit == "flag":
        beyond = threshold.level(value) > 0
        return ThresholdRow(name, "yes" if value >= 0.5 else "no", "set or not", LEVEL_WORDS[1], "—",
                            "beyond" if beyond else "within", LEVEL_WORDS.get(level, "?"), math.inf)
    limits = [(limit, lv) for limit, lv in ((threshold.some, 1), (threshold.failure, 2)) if limit is not None]
    if not limits:
        return None
    limit, limit_level = min(limits, key=lambda pair: _distance(name, value, pair[0]))
    op = ">" if rule.direction == "above" else "<"
    beyond = value > limit if rule.direction == "above" else value < limit
    scale = 100.0 if rule.unit in ("percent", "percent1") else 1.0
    difference = (value - limit) * scale
    unit = {"px": " px", "deg": " deg", "percent": " points", "percent1": " points"}.get(rule.unit, "")
    decimals = 2 if rule.unit in ("percent", "percent1", "ratio") else (1 if rule.unit in ("px", "deg") else 3)
    margin = f"{difference:+.{decimals}f}{unit}"
    if round(difference, decimals) == 0:
        margin = f"{difference:+.{decimals + 3}f}{unit}"
    return ThresholdRow(name, _format(value, rule.unit, limit), f"{op} {_threshold_text(limit, rule.unit)}",
                        LEVEL_WORDS[limit_level], margin, "beyond" if beyond else "within",
                        LEVEL_WORDS.get(level, "?"), _distance(name, value, limit))


def threshold_table(metrics: dict[str, Any] | None) -> ThresholdTable | None:
    """The table for a grade record's ``metrics``; None when it holds no per-measurement levels."""
    metrics = metrics or {}
    nested = metrics.get("measurements")
    measurements: dict[str, Any] = nested if isinstance(nested, dict) else metrics
    levels = metrics.get("levels")
    if not isinstance(levels, dict) or not levels:
        return None
    threshold_source = metrics.get("thresholds")
    known = False
    thresholds = None
    if isinstance(threshold_source, dict):
        from pipeline.errors import InvalidInputError
        from pipeline.grading import GradeThresholds

        try:
            thresholds, known = GradeThresholds.from_dict(threshold_source), True
        except InvalidInputError:
            thresholds = None
    if thresholds is None:
        thresholds, known = _thresholds_for(metrics)
    rows = []
    for name, level in levels.items():
        value = _number(measurements.get(name))
        if value is None or not isinstance(level, int):
            continue
        row = _row(name, value, level, getattr(thresholds, name, None)) if hasattr(thresholds, name) else None
        if row is not None:
            rows.append(row)
    rows.sort(key=lambda row: row.distance)
    recorded = metrics.get("nearest")
    if isinstance(recorded, dict) and recorded.get("measurement") in {row.measurement for row in rows}:
        nearest = next(row for row in rows if row.measurement == recorded["measurement"])
        return ThresholdTable(rows, nearest, known, True)
    finite = [row for row in rows if math.isfinite(row.distance)]
    return ThresholdTable(rows, finite[0] if finite else None, known, False)

