"""The verdict: thresholds per measurement, the grade (few / some / failure), its reasons in words
and its uncertainty.

:func:`grade` compares :class:`~pipeline.grading.measurements.GradeMeasurements` with a
:class:`GradeThresholds`; the worst level any measurement reaches is the grade, and every grade
carries its reasons ("failure: rows of the two views are misaligned by 6.1 px (> 3 px)").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

from ..errors import InvalidInputError
from .measurements import GradeMeasurements

__all__ = ["GRADES", "RULES", "GradeParams", "GradeResult", "GradeThresholds", "Threshold", "grade", "paper_distribution"]

Grade = Literal["few", "some", "failure"]
GRADES: tuple[Grade, Grade, Grade] = ("few", "some", "failure")
Direction = Literal["above", "below"]

UNCERTAINTY_SPAN = math.log(4.0)  # a factor of 4 from the nearest threshold that matters gives 0


def paper_distribution() -> dict[str, float]:
    """The paper's hand-graded distribution: 23 % few artifacts, 49 % some, 28 % failure.

    Source: Luo, Kong, Lawrence, Martin-Brualla, Seitz, "KeystoneDepth: History in 3D"
    (3DV 2020), the quality assessment of a random sample of 711 processed cards.
    Reports compare the automatic and curated grades with it.
    """
    return {"few": 0.23, "some": 0.49, "failure": 0.28}


@dataclass(frozen=True)
class Threshold:
    """One measurement's rule. ``direction`` ``above``: values above ``some`` / ``failure`` are
    artifacts (``>``); ``below``: values under them are (``<``). A ``None`` level is not used."""

    direction: Direction
    some: float | None
    failure: float | None

    def level(self, value: float) -> int:
        """0 few, 1 some, 2 failure."""

        def beyond(threshold: float) -> bool:
            return value > threshold if self.direction == "above" else value < threshold

        if self.failure is not None and beyond(self.failure):
            return 2
        if self.some is not None and beyond(self.some):
            return 1
        return 0


@dataclass(frozen=True)
class _Rule:
    """How a measurement reads in words, and how its distance to a threshold is scaled
    (``span``: for the ``linear`` scale, the difference that counts as far as a factor of 4)."""

    direction: Direction
    scale: Literal["ratio", "complement", "excess", "flag", "linear"]
    words: str  # format with {v} (the value formatted by ``unit``)
    unit: Literal["px", "deg", "ratio", "percent", "percent1", "number", "flag"]
    span: float = 0.0


RULES: dict[str, _Rule] = {
    "good_match_fraction": _Rule("below", "ratio", "only {v} of the keypoints match between the halves", "percent1"),
    "dy_p95_px": _Rule("above", "ratio", "rectified matches still differ by {v} in height (95th percentile)", "px"),
    "shear_deg": _Rule("above", "ratio", "rectification sheared {v}", "deg"),
    "aspect_change": _Rule("above", "excess", "rectification changed the aspect ratio by x{v}", "ratio"),
    "rotation_deg": _Rule("above", "ratio", "rectification turned a view by {v}", "deg"),
    "kept_fraction": _Rule("below", "complement", "rectification kept only {v} of a view", "percent"),
    "swapped": _Rule(
        "above", "flag", "eyes swapped on the card (the halves were exchanged: check the depth is not reversed)", "flag"
    ),
    "row_misalignment_px": _Rule("above", "ratio", "rows of the two views are misaligned by {v}", "px"),
    "coverage": _Rule("below", "complement", "disparity covers {v} of the view", "percent"),
    "lr_consistency": _Rule("below", "complement", "left and right disparities agree on only {v} of the pixels", "percent"),
    "confident_fraction": _Rule("below", "complement", "only {v} of the disparities are confident", "percent"),
    "disparity_range_rel": _Rule(
        "below", "ratio", "disparity spans only {range_px} ({v} of the width): little depth to see", "percent1"
    ),
    "textured_fraction": _Rule("below", "ratio", "low texture: only {v} of the view is textured", "percent"),
    "photometric_error_rel": _Rule(
        "above",
        "ratio",
        "the right view warped by the disparity misses the left by {grey} on "
        "average, {v} of the difference between unrelated images",
        "number",
    ),
    "depth_order": _Rule(
        "below",
        "linear",
        "the depth ordering reads {v}: the top of the picture comes out nearer than "
        "the bottom (upside down, eyes swapped, or a near blob high up)",
        "number",
        span=0.5,
    ),
    "streak_fraction": _Rule(
        "above",
        "ratio",
        "{v} of the disparity is row streaks (runs along rows that break against the rows above and below)",
        "percent",
    ),
    "sky_near_fraction": _Rule(
        "above",
        "ratio",
        "{v} of the upper half is textureless (sky, blank print) yet reads nearer than the textured scene",
        "percent",
    ),
    "reflection_symmetry": _Rule(
        "above",
        "linear",
        "the picture mirrors itself about row {horizon} in intensity and depth "
        "(symmetry {v}): a reflection read as a second scene",
        "number",
        span=0.3,
    ),
    "border_line": _Rule(
        "above",
        "ratio",
        "a straight edge with a plain strip outside it runs along {v} of the {side} border: card edge or mount inside the crop",
        "percent",
    ),
    "border_strokes": _Rule(
        "above", "ratio", "{v} of a border strip is ink-like strokes: mount text or a caption inside the crop", "percent1"
    ),
}


_DECIMALS = {"px": 1, "deg": 1, "ratio": 2, "percent": 0, "percent1": 2, "number": 3}


def _format(value: float, unit: str, beside: float | None = None) -> str:
    """A value in its unit; with ``beside`` (the threshold it is compared with), enough decimals
    that the two never print alike ("59.7 % (< 60 %)", not "60 % (< 60 %)")."""
    scale = 100.0 if unit in ("percent", "percent1") else 1.0
    decimals = _DECIMALS.get(unit, 3)
    if beside is not None and value != beside:
        while decimals < 6 and round(value * scale, decimals) == round(beside * scale, decimals):
            decimals += 1
    text = f"{value * scale:.{decimals}f}"
    return {"px": f"{text} px", "deg": f"{text} deg", "percent": f"{text} %", "percent1": f"{text} %"}.get(unit, text)


def _context(m: GradeMeasurements) -> dict[str, str]:
    """Companion figures some reasons quote beside their own value."""

    def show(value: float | None, text: str) -> str:
        return "?" if value is None else text.format(value)

    return {
        "range_px": show(m.disparity_range_px, "{:.1f} px"),
        "grey": show(m.photometric_error, "{:.1f} grey levels"),
        "horizon": show(m.reflection_row_px, "{:.0f}"),
        "side": m.border_side or "crop's",
    }


def _threshold_text(threshold: float, unit: str) -> str:
    """Thresholds print as short as they are exact: 80 %, 3 px, 0.5 %, 1.15."""
    if unit in ("percent", "percent1"):
        return f"{100 * threshold:.6g} %"
    if unit in ("px", "deg"):
        return f"{threshold:.6g} {unit}"
    return f"{threshold:.6g}"


@dataclass(frozen=True)
class GradeThresholds:
    """The grade's thresholds, one :class:`Threshold` per graded measurement.

    Defaults, and why (measured figures from this module's tests and docs/BENCHMARKS.md):

    * ``good_match_fraction``: true pairs match 20-34 % of keypoints, unrelated images 0.25-0.45 %,
      the filter culls below 0.5 % and asks people between 0.5 and 1.5 %: under 3 % a pair is
      weakly related (some), under 1 % it is barely a pair (failure).
    Pixel measurements are in px at a view 600 px on its longer side
    (:data:`pipeline.grading.measurements.REFERENCE_SIDE`), so one card grades alike at any scan size.

    * ``dy_p95_px``: rectification refuses a p95 above 2 px (``RectifyParams.max_dy_p95``). On
      ``keystone bench grade`` the accepted 0.9-2.0 px did not follow the true error (Spearman
      -0.18: it is SIFT's noise on print grain; ``row_misalignment_px`` measures the parallax a
      viewer sees): over 2 px some (reachable when rectification's own limit is loosened), 3 px
      makes fusion hard (failure).
    * ``shear_deg``: Loop-Zhang keeps midlines perpendicular to ~0.01 deg; OpenCV's Hartley method
      sheared a good pair by 6 deg with wrong disparities: 3 deg some, 8 deg failure.
    * ``aspect_change``: 1.15 visibly squashes people and buildings (some); 1.35 is close to
      rectification's own refusal at 1.5 (failure).
    * ``rotation_deg``: period stereo cameras were levelled; 4 deg is a visibly tilted horizon
      (some), 9 deg is near rectification's 10 deg refusal, the mark of a wrong F (failure).
    * ``kept_fraction``: rectification refuses under 50 %; under 85 % a view lost a visible
      part (some), under 60 % most of the scene's edge is gone (failure).
    * ``swapped``: a detected and corrected swap is some artifacts: if the detection was wrong
      the depth is reversed (the curators' "Flip"), so a person should look.
    * ``row_misalignment_px``: Middlebury's rectified pairs (Motorcycle, Tsukuba, Adirondack)
      read under 0.15 px, the Motorcycle pair (741 px) with its right view 6 px down reads 4.9 px
      (6 px x 600 / 741), and unrectified antique pairs 1-10 px: 2 px is visible vertical parallax
      (some), 4 px strains fusion (failure). These were measured on views of 600-741 px, so they
      stay 2 / 4 px at the 600 px reference (measured 2026-11-28: 1.5 / 3 px, the same fraction of
      an 800 px view, turned a bench card of true bad-2 40 % into a failure and the Spearman of
      ``keystone bench grade`` from 0.62 to 0.58). Until 2026-11-28 this was px of the stored
      view, which grows with the scan up to 800 px: the same card graded few at its size and
      some at 4x.
    * ``coverage``: the default backend covers 100 %, StereoSGBM 82-86 %: under 80 % holes show
      (some), under 50 % the depth map is mostly missing (failure).
    * ``lr_consistency``: the default backend's maps agree on 84-96 % of Middlebury pairs and
      70-93 % of antique ones, 14 % of unrelated images; on ``keystone bench grade`` cards 44-78 %,
      falling as the true bad-2 rises (Spearman -0.46): under 70 % (below the antique range) some,
      under 50 % failure.
    * ``confident_fraction``: Middlebury 68-78 %, antique pairs 29-71 %, unrelated images 2 %;
      bench cards 18-58 % (Spearman -0.45 with the true bad-2): under 45 % some, under 25 % failure.
    * ``disparity_range_rel``: p95 - p5 of the disparity over the width. Motorcycle spans ~6 %;
      antique cards of distant scenes ~1 %. Under 0.5 % (3.5 px on a 700 px view) the depth map
      is nearly flat (some); under 0.15 % (about 1 px) there is no depth to see (failure: the
      curators' "All-Blue").
    * ``textured_fraction``: share of the view steeper than 3 grey levels / px at 512 px. Real
      photographs measure 36-87 % (Middlebury and antique pairs); under 15 % matching is
      unreliable (some), under 4 % the view is nearly blank (failure).
    * ``depth_order``: Motorcycle reads +0.65 (ground truth and the default backend alike),
      the same map upside down or reversed -0.66; bench cards with swapped eyes -0.58 and -0.34,
      the others -0.03..+0.65: under -0.1 the top reads nearer than the bottom (some), under -0.25
      the depth is most likely reversed (failure: the curators' "Flip").
    * ``streak_fraction``: clean disparity on Motorcycle 0 %; a map with a 3-row streak every 12
      rows 38 % (24 % on a plane): over 5 % streaks show (some), over 20 % they are much of the map (failure: the
      careful person's "about 70 % of the map is streaks" card).
    * ``sky_near_fraction``: Motorcycle 0-4 %; a flat sky at the 90th percentile of disparity
      over 30 % of the height 55 %: over 8 % a false near blob shows (some), over 30 % (failure).
    * ``reflection_symmetry``: photographs without reflections 0.28-0.35, a mirrored lower half
      0.90: over 0.6 is a reflection read as depth (some; never failure alone).
    * ``border_line``: Motorcycle 0.12, a 40 px plain mount strip on top 0.79, the filter's split
      of simulated cards 0.99. Off by default (always measured and listed in ``checks``): a mount
      strip did not change the true error on the bench (Spearman 0.12) and the careful person
      graded a card with caption in its crop few; set a some threshold (0.6) to flag it.
      ``border_strokes``: 0 without text, 3 % with a caption line in the top strip, bench cards
      0-3.7 %: over 5 % the crop holds much mount text (some).
    * ``photometric_error_rel``: Middlebury pairs 0.06-0.10, antique pairs (different prints,
      residual misalignment) 0.31-0.44, Motorcycle with the right view 6 px down 0.50,
      unrelated images 0.93: above 0.5 the disparity does not explain the pair (some), above
      0.75 it hardly relates the views (failure).
    """

    good_match_fraction: Threshold = Threshold("below", 0.03, 0.01)
    dy_p95_px: Threshold = Threshold("above", 2.0, 3.0)
    shear_deg: Threshold = Threshold("above", 3.0, 8.0)
    aspect_change: Threshold = Threshold("above", 1.15, 1.35)
    rotation_deg: Threshold = Threshold("above", 4.0, 9.0)
    kept_fraction: Threshold = Threshold("below", 0.85, 0.6)
    swapped: Threshold = Threshold("above", 0.5, None)
    row_misalignment_px: Threshold = Threshold("above", 2.0, 4.0)
    coverage: Threshold = Threshold("below", 0.8, 0.5)
    lr_consistency: Threshold = Threshold("below", 0.7, 0.5)
    confident_fraction: Threshold = Threshold("below", 0.45, 0.25)
    disparity_range_rel: Threshold = Threshold("below", 0.005, 0.0015)
    textured_fraction: Threshold = Threshold("below", 0.15, 0.04)
    photometric_error_rel: Threshold = Threshold("above", 0.5, 0.75)
    depth_order: Threshold = Threshold("below", -0.1, -0.25)
    streak_fraction: Threshold = Threshold("above", 0.05, 0.2)
    sky_near_fraction: Threshold = Threshold("above", 0.08, 0.3)
    reflection_symmetry: Threshold = Threshold("above", 0.6, None)
    border_line: Threshold = Threshold("above", None, None)
    border_strokes: Threshold = Threshold("above", 0.05, None)

    def __post_init__(self) -> None:
        for name, spec in RULES.items():
            rule: Threshold = getattr(self, name)
            if not isinstance(rule, Threshold):
                raise InvalidInputError(f"{name}: expected a Threshold, got {type(rule).__name__}")
            if rule.direction != spec.direction:
                raise InvalidInputError(
                    f"{name}: direction must be {spec.direction!r} (what the measurement means), got {rule.direction!r}"
                )
            for level in ("some", "failure"):
                value = getattr(rule, level)
                if value is not None and (
                    isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
                ):
                    raise InvalidInputError(f"{name}.{level}: expected a finite number or null, got {value!r}")
            if rule.some is not None and rule.failure is not None:
                ordered = rule.failure >= rule.some if rule.direction == "above" else rule.failure <= rule.some
                if not ordered:
                    raise InvalidInputError(
                        f"{name}: the failure threshold {rule.failure} must be beyond the some threshold "
                        f"{rule.some} ({rule.direction})"
                    )

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """``{measurement: {"direction", "some", "failure"}}`` (JSON-safe)."""
        return {
            name: {"direction": t.direction, "some": t.some, "failure": t.failure}
            for name, t in ((n, getattr(self, n)) for n in RULES)
        }

    @classmethod
    def from_dict(cls, document: Mapping[str, Any]) -> GradeThresholds:
        """Read :meth:`to_dict` output. Measurements it leaves out keep their defaults; an unknown
        measurement, a wrong direction or a non-numeric threshold raises :class:`InvalidInputError`."""
        if not isinstance(document, Mapping):
            raise InvalidInputError(f"Expected a mapping of thresholds, got {type(document).__name__}")
        unknown = sorted(set(document) - set(RULES))
        if unknown:
            raise InvalidInputError(f"unknown grade measurements: {', '.join(map(str, unknown))}")
        defaults = cls()
        kwargs: dict[str, Threshold] = {}
        for name, entry in document.items():
            if not isinstance(entry, Mapping):
                raise InvalidInputError(f"{name}: expected {{direction, some, failure}}, got {entry!r}")
            base = getattr(defaults, name)
            values = {}
            for level in ("some", "failure"):
                raw = entry.get(level, getattr(base, level))
                values[level] = float(raw) if isinstance(raw, (int, float)) and not isinstance(raw, bool) else raw
            kwargs[name] = Threshold(entry.get("direction", base.direction), values["some"], values["failure"])
        return replace(defaults, **kwargs)


@dataclass(frozen=True)
class GradeParams:
    """The grade stage's parameters (hashed by :func:`pipeline.records.param_hash`)."""

    thresholds: GradeThresholds = field(default_factory=GradeThresholds)


@dataclass(frozen=True)
class GradeResult:
    """``grade`` few / some / failure; ``reasons`` in words, the deciding ones first, then the
    lesser ones, then the nearest threshold, then notes on what was not measured; ``deciding``:
    the measurements at the grade's level (empty for few); ``uncertainty`` in [0, 1] (see
    :func:`grade`) and ``uncertainty_reason``, the sentence that explains it; ``levels``: each
    measured rule's level (0 few, 1 some, 2 failure).

    ``nearest``: the measurement nearest a threshold whose crossing would change the grade
    (``None`` when no measured threshold can): ``{"measurement", "value", "threshold", "margin",
    "level", "distance", "changes_grade", "grade_if_crossed"}``, where ``level`` is the threshold's (``some`` or
    ``failure``), ``margin`` = value - threshold in the measurement's own unit, and ``distance``
    the scaled distance the uncertainty comes from. When no threshold can change the grade
    (a failure decided by two measurements), ``nearest`` is the nearest threshold of all with
    ``changes_grade`` false. ``checks``: one row per graded measurement for a table
    ``{"measurement", "value", "unit", "direction", "some", "failure", "level", "margin",
    "distance"}`` (``level`` few / some / failure; ``margin`` and ``distance`` to the nearer of
    its thresholds; a missing value has ``value`` ``None`` and a ``note``)."""

    grade: Grade
    reasons: list[str]
    uncertainty: float
    deciding: list[str]
    levels: dict[str, int]
    notes: list[str]
    nearest: dict[str, Any] | None = None
    checks: list[dict[str, Any]] = field(default_factory=list)
    uncertainty_reason: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _distance(name: str, value: float, threshold: float) -> float:
    """Log-ratio distance of a value from a threshold, on the scale the measurement lives on."""
    scale = RULES[name].scale
    if scale == "flag":
        return math.inf  # a flag is set or not: never "near" its threshold
    if scale == "linear":  # signed values: a difference of ``span`` is as far as a factor of 4
        return abs(value - threshold) / RULES[name].span * UNCERTAINTY_SPAN
    if scale == "complement":  # fractions near 1: compare what is missing (5 % vs 20 % missing)
        value, threshold = 1.0 - value, 1.0 - threshold
    elif scale == "excess":  # ratios >= 1: compare the excess over 1
        value, threshold = value - 1.0, threshold - 1.0
    tiny = 1e-9
    return abs(math.log(max(value, tiny) / max(threshold, tiny)))


def _threshold_entry(name: str, value: float, limit: float, level_name: str, grade_now: int, grade_across: int) -> dict[str, Any]:
    distance = _distance(name, value, limit)
    return {
        "measurement": name,
        "value": round(value, 6),
        "threshold": limit,
        "margin": round(value - limit, 6),
        "level": level_name,
        "distance": None if not math.isfinite(distance) else round(distance, 4),
        "changes_grade": grade_across != grade_now,
        "grade_if_crossed": GRADES[grade_across],
    }


def _far(entry: dict[str, Any]) -> float:
    """An entry's distance, a flag's (never near) as infinity."""
    return math.inf if entry["distance"] is None else float(entry["distance"])


def _nearest_text(entry: dict[str, Any]) -> str:
    """ "coverage 83 % is 3 points from its some threshold (< 80 %)"."""
    name = entry["measurement"]
    rule = RULES[name]
    value, limit = entry["value"], entry["threshold"]
    op = ">" if rule.direction == "above" else "<"
    if rule.unit in ("percent", "percent1"):
        gap = f"{abs(value - limit) * 100:.{2 if rule.unit == 'percent1' else 0}f} points"
    elif rule.unit in ("px", "deg"):
        gap = f"{abs(value - limit):.2f} {rule.unit}"
    else:
        gap = f"{abs(value - limit):.3g}"
    return (
        f"{name} {_format(value, rule.unit, limit)} is {gap} from its {entry['level']} threshold "
        f"({op} {_threshold_text(limit, rule.unit)})"
    )


def grade(measurements: GradeMeasurements | Mapping[str, Any], thresholds: GradeThresholds | None = None) -> GradeResult:
    """Grade a card: the worst level any measured rule reaches (few < some < failure).

    A rule whose measurement is missing is skipped, with a note. ``uncertainty`` is
    ``max(0, 1 - d / ln 4)`` where ``d`` is the distance between a measurement and the nearest
    threshold *that matters*: one whose crossing, every other measurement staying put, would
    change the grade (for a few card every first threshold; for a failure decided by two
    measurements none). ``d`` is the log-ratio ``|ln(value / threshold)|`` for most measurements;
    fractions near 1 (coverage, consistency, confidence, kept area) compare what is missing,
    ``1 - value``; the aspect change compares its excess over 1; signed measurements (depth
    order, reflection symmetry) use ``|value - threshold| / span * ln 4``; flags are never near.
    1 = a measurement sits on such a threshold, 0 = every one is at least a factor of 4 away.
    The result names that threshold (``nearest``) and says so in ``uncertainty_reason``.
    """
    thresholds = thresholds if thresholds is not None else GradeThresholds()
    m = GradeMeasurements.from_dict(measurements) if not isinstance(measurements, GradeMeasurements) else measurements
    levels: dict[str, int] = {}
    values: dict[str, float] = {}
    notes: list[str] = []
    checks: list[dict[str, Any]] = []
    for name, rule in RULES.items():
        raw = getattr(m, name)
        threshold = getattr(thresholds, name)
        if raw is None:
            why = m.note_for(name) or "not measured"
            notes.append(f"note: {name} not graded ({why})")
            checks.append(
                {
                    "measurement": name,
                    "value": None,
                    "unit": rule.unit,
                    "direction": threshold.direction,
                    "some": threshold.some,
                    "failure": threshold.failure,
                    "level": None,
                    "margin": None,
                    "distance": None,
                    "note": why,
                }
            )
            continue
        value = float(raw)
        values[name] = value
        levels[name] = threshold.level(value)
    worst = max(levels.values(), default=0)
    deciding = [name for name, level in levels.items() if level == worst] if worst > 0 else []

    reasons: list[str] = []
    for level in (2, 1):
        for name, reached in levels.items():
            if reached != level:
                continue
            rule, threshold = RULES[name], getattr(thresholds, name)
            limit = threshold.failure if level == 2 else threshold.some
            text = rule.words.format(v=_format(values[name], rule.unit, limit), **_context(m))
            if rule.unit != "flag":
                op = ">" if rule.direction == "above" else "<"
                text += f" ({op} {_threshold_text(limit, rule.unit)})"
            reasons.append(f"{GRADES[level]}: {text}")

    mattering: dict[str, Any] | None = None
    any_nearest: dict[str, Any] | None = None
    for name, level in levels.items():
        threshold = getattr(thresholds, name)
        others = max((lv for other, lv in levels.items() if other != name), default=0)
        own_nearest: dict[str, Any] | None = None
        for limit, level_name in ((threshold.some, "some"), (threshold.failure, "failure")):
            if limit is None:
                continue
            # The measurement's level just across this threshold from where it is now, and
            # whether the grade would then change.
            eps = 1e-9 * max(1.0, abs(limit))
            above, below = threshold.level(limit + eps), threshold.level(limit - eps)
            if values[name] != limit:
                across = above if values[name] < limit else below
            else:  # sitting on the threshold: across is whichever side is not its own level
                across = above if above != level else below
            entry = _threshold_entry(name, values[name], limit, level_name, worst, max(others, across))
            distance = _far(entry)
            if own_nearest is None or distance < _far(own_nearest):
                own_nearest = entry
            if any_nearest is None or distance < _far(any_nearest):
                any_nearest = entry
            if entry["changes_grade"] and math.isfinite(distance) and (mattering is None or distance < _far(mattering)):
                mattering = entry
        checks.append(
            {
                "measurement": name,
                "value": round(values[name], 6),
                "unit": RULES[name].unit,
                "direction": threshold.direction,
                "some": threshold.some,
                "failure": threshold.failure,
                "level": GRADES[level],
                "margin": None if own_nearest is None else own_nearest["margin"],
                "distance": None if own_nearest is None else own_nearest["distance"],
            }
        )
    checks.sort(key=lambda row: list(RULES).index(row["measurement"]))

    nearest = (
        mattering
        if mattering is not None
        else (any_nearest if any_nearest is not None and any_nearest["distance"] is not None else None)
    )
    if mattering is not None:
        uncertainty = max(0.0, 1.0 - mattering["distance"] / UNCERTAINTY_SPAN)
        uncertainty_reason = (
            f"uncertainty {uncertainty:.2f}: {_nearest_text(mattering)}; crossing it would make "
            f"the grade {mattering['grade_if_crossed']} "
            f"(1 = on the threshold, 0 = a factor of 4 or more away)"
        )
    else:
        uncertainty = 0.0
        uncertainty_reason = (
            "uncertainty 0.00: no single measurement crossing a threshold would change the grade"
            if levels
            else "uncertainty 0.00: nothing was measured"
        )
    if worst == 0:
        summary = f"few: every measurement within thresholds ({len(levels)} of {len(RULES)} measured)"
        if nearest is not None:
            summary += f"; nearest: {_nearest_text(nearest)}"
        reasons.append(summary)
    elif nearest is not None and nearest["measurement"] not in deciding:
        reasons.append(f"nearest: {_nearest_text(nearest)}")
    return GradeResult(
        grade=GRADES[worst],
        reasons=reasons + notes,
        uncertainty=round(uncertainty, 4),
        deciding=deciding,
        levels=levels,
        notes=notes,
        nearest=nearest,
        checks=checks,
        uncertainty_reason=uncertainty_reason,
    )
