"""The automatic quality grade of a card: few artifacts / some artifacts / failure, with reasons.

The paper (KeystoneDepth, Luo et al.) graded a sample of 711 cards by hand into these three
categories (:func:`paper_distribution`). Here every card gets the grade automatically from
measurements the pipeline already has, each compared with two thresholds ("some" and
"failure"); the worst level any measurement reaches is the grade, and every grade carries its
reasons in words ("failure: rows of the two views are misaligned by 6.1 px (> 3 px)").

Three steps, all pure:

* :func:`measure_card` turns the rectified views, both disparity maps, their confidence and the
  earlier stages' metrics into a :class:`GradeMeasurements` (units in its docstring).
* :func:`grade` compares them with a :class:`GradeThresholds` and returns a :class:`GradeResult`:
  the grade, the reasons, the deciding measurements and an ``uncertainty`` for the curators'
  queue (definition in :func:`grade`).
* :func:`fit_thresholds` refits the thresholds to curator labels (coordinate descent over
  candidate thresholds at the measurements' quantiles, maximising macro-F1) and reports the
  agreement on labels the thresholds were not fitted on (k-fold cross-validation).

:func:`pipeline.stages.grade.grade_task` is the per-card stage task the runner calls.

Conventions as in :mod:`pipeline.disparity`: a left pixel ``(x, y)`` is seen in the right view at
``x_right = x_left - d_left``; a right pixel at ``x_left = x_right + d_right``. Views are uint8
``(H, W)`` grey or ``(H, W, 3)`` RGB; pixels that are 0 in every channel of a view are the
warp's black fill, outside the photograph.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Literal

import cv2
import numpy as np

from .disparity import ImageTooSmallError
from .errors import InvalidInputError, PipelineError
from .io import to_grey

__all__ = [
    "GRADES",
    "FitReport",
    "GradeMeasurements",
    "GradeParams",
    "GradeResult",
    "GradeThresholds",
    "NotEnoughLabelsError",
    "Threshold",
    "agreement",
    "fit_thresholds",
    "grade",
    "measure_card",
    "paper_distribution",
]

GRADES: tuple[str, ...] = ("few", "some", "failure")
Grade = Literal["few", "some", "failure"]
Direction = Literal["above", "below"]

MIN_SIDE = 16  # px: as the disparity stage; smaller views have nothing to measure
WORK_SIDE = 512  # px: texture and row alignment are measured at this longer side (see measure_card)
TEXTURE_GRADIENT = 3.0  # grey levels / px at WORK_SIDE: a pixel at least this steep counts as textured
CONSISTENCY_PX = 1.0  # left-right check tolerance (px), as the disparity stage's default
MIN_LABELS = 10  # fewer curator labels cannot be cross-validated meaningfully
UNCERTAINTY_SPAN = math.log(4.0)  # a factor of 4 from the nearest threshold that matters gives 0


def paper_distribution() -> dict[str, float]:
    """The paper's hand-graded distribution: 23 % few artifacts, 49 % some, 28 % failure.

    Source: Luo, Kong, Lawrence, Martin-Brualla, Seitz, "KeystoneDepth: History in 3D"
    (3DV 2020), the quality assessment of a random sample of 711 processed cards (also in
    ``DESIGN.md``, flow step 8). Reports compare the automatic and curated grades with it.
    """
    return {"few": 0.23, "some": 0.49, "failure": 0.28}


class NotEnoughLabelsError(PipelineError):
    """Too few curator labels (or a single class) to fit and cross-validate thresholds."""

    code = "not_enough_labels"


# ------------------------------------------------------------------------------- measurements


@dataclass(frozen=True)
class GradeMeasurements:
    """What the grade is computed from. ``None`` = not measured (``notes`` says why).

    From the filter stage:

    * ``good_match_fraction``: SIFT ratio-test matches / keypoints between the halves (0..1).

    From the rectify stage (the worse of the two views where it measures both):

    * ``dy_p95_px``: px, 95th percentile of inlier ``|y_l - y_r|`` after rectification.
    * ``shear_deg``: deg, ``90 - midline_angle``: how far the images of the midlines are from
      perpendicular (0 = no shear).
    * ``aspect_change``: ratio >= 1, change of the midline length ratio (1 = none).
    * ``rotation_deg``: deg, ``|in-plane rotation|`` of a view.
    * ``kept_fraction``: smallest share (0..1) of a view's warped area inside the output.
    * ``swapped``: the eyes were swapped on the card (the halves were exchanged).

    Measured here from the rectified views and the disparity maps:

    * ``row_misalignment_px``: px at full resolution, largest ``|v|`` at the four corners of a
      robust plane ``v = c0 + c1 x + c2 y`` fitted to the vertical component of DIS optical flow
      from the left to the right view over textured pixels (at ``WORK_SIDE``): what a viewer sees
      as vertical parallax, whatever the rectification reported.
    * ``coverage``: share (0..1) of the left view's photograph (non-black pixels) with a finite
      left disparity (NaN, inf and ``|d|`` above the view width count as none).
    * ``lr_consistency``: share (0..1) of covered left pixels whose match ``x - d_L`` lies inside
      the right view with ``|d_L(x) - d_R(x - d_L(x))| <= 1 px`` (``d_R`` at the nearest pixel).
    * ``confident_fraction``: share (0..1) of the photograph with confidence >= 0.5.
    * ``disparity_range_px``: px, p95 - p5 of the finite left disparities on the photograph;
      ``disparity_range_rel`` is the same over the view width (0.05 = 5 % of the width).
    * ``texture_gradient``: grey levels per px, median Sobel gradient magnitude of the grey left
      view at ``WORK_SIDE``; ``textured_fraction``: share (0..1) of the photograph at least
      ``TEXTURE_GRADIENT`` steep there.
    * ``photometric_error``: grey levels (0..255), mean ``|L(x, y) - R(x - d_L, y)|`` over covered
      pixels whose match falls on the right photograph, after removing the median brightness
      difference between the views. ``photometric_error_rel``: the same after normalising each
      view to zero mean and unit mean absolute deviation over those pixels, divided by sqrt(2):
      0 = the warped right view reproduces the left, about 1 = as different as two unrelated
      images (for roughly Gaussian intensities); gain and offset between the prints cancel.
    """

    good_match_fraction: float | None = None
    dy_p95_px: float | None = None
    shear_deg: float | None = None
    aspect_change: float | None = None
    rotation_deg: float | None = None
    kept_fraction: float | None = None
    swapped: bool | None = None
    row_misalignment_px: float | None = None
    coverage: float | None = None
    lr_consistency: float | None = None
    confident_fraction: float | None = None
    disparity_range_px: float | None = None
    disparity_range_rel: float | None = None
    texture_gradient: float | None = None
    textured_fraction: float | None = None
    photometric_error: float | None = None
    photometric_error_rel: float | None = None
    notes: tuple[tuple[str, str], ...] = ()  # (measurement, why it is missing)

    def as_dict(self) -> dict[str, Any]:
        """JSON-safe ``{name: float | bool | None}`` (no NaN; notes are not included)."""
        out: dict[str, Any] = {}
        for name in _MEASUREMENT_NAMES:
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)):
                out[name] = bool(value)
            elif value is None or not math.isfinite(float(value)):
                out[name] = None
            else:
                out[name] = round(float(value), 6)
        return out

    def note_for(self, name: str) -> str | None:
        return dict(self.notes).get(name)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> GradeMeasurements:
        """Read :meth:`as_dict` output (or a grade record's metrics: other keys are ignored).
        Non-numeric or non-finite values become ``None``."""
        if isinstance(values, GradeMeasurements):
            return values
        if not isinstance(values, Mapping):
            raise InvalidInputError(f"Expected a mapping of grade measurements, got {type(values).__name__}")
        kwargs: dict[str, Any] = {}
        for name in _MEASUREMENT_NAMES:
            value = values.get(name)
            if name == "swapped":
                kwargs[name] = None if value is None else bool(value)
            else:
                kwargs[name] = _finite_or_none(value)
        return cls(**kwargs)


_MEASUREMENT_NAMES: tuple[str, ...] = tuple(f.name for f in fields(GradeMeasurements) if f.name != "notes")


def _finite_or_none(value: Any) -> float | None:
    if value is None or isinstance(value, (str, bytes, list, dict, tuple)):
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def _check_view(image: Any, name: str) -> np.ndarray:
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3):
        raise InvalidInputError(f"{name}: expected (H, W) or (H, W, 3), got shape {array.shape}")
    if array.dtype != np.uint8:
        raise InvalidInputError(f"{name}: expected uint8 pixels, got {array.dtype}")
    if min(array.shape[:2]) < MIN_SIDE:
        raise ImageTooSmallError(f"{name}: {array.shape[1]}x{array.shape[0]} is below {MIN_SIDE} px on a side")
    return array


def _check_map(values: Any, name: str, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(values)
    if array.shape != shape:
        raise InvalidInputError(f"{name}: expected shape {shape} (the views'), got {array.shape}")
    if array.dtype.kind not in "fiu":
        raise InvalidInputError(f"{name}: expected a numeric map, got {array.dtype}")
    return array.astype(np.float32, copy=False)


def _photograph(view: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels of the photograph (not the warp's black fill)."""
    return view.reshape(*view.shape[:2], -1).max(axis=2) > 0


def _rectify_values(rectify: Mapping[str, Any], notes: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    out["dy_p95_px"] = _finite_or_none(rectify.get("dy_p95"))
    angle = _finite_or_none(rectify.get("midline_angle"))
    out["shear_deg"] = None if angle is None else abs(90.0 - angle)
    out["aspect_change"] = _finite_or_none(rectify.get("aspect_change"))
    rotation = _finite_or_none(rectify.get("rotation"))
    out["rotation_deg"] = None if rotation is None else abs(rotation)
    out["kept_fraction"] = _finite_or_none(rectify.get("kept_fraction"))
    swapped = rectify.get("swapped")
    out["swapped"] = None if swapped is None else bool(swapped)
    why = "no rectify metrics" if not rectify else "not in the rectify metrics"
    for name, value in out.items():
        if value is None:
            notes[name] = why
    return out


def _row_misalignment(grey_l: np.ndarray, grey_r: np.ndarray, inside: np.ndarray) -> float | None:
    """px at full resolution (see :class:`GradeMeasurements`); None without textured pixels."""
    h, w = grey_l.shape
    scale = min(1.0, WORK_SIDE / max(h, w))
    size = (max(MIN_SIDE, round(w * scale)), max(MIN_SIDE, round(h * scale)))
    small_l = cv2.resize(grey_l, size, interpolation=cv2.INTER_AREA) if scale < 1 else grey_l
    small_r = cv2.resize(grey_r, size, interpolation=cv2.INTER_AREA) if scale < 1 else grey_r
    mask = cv2.resize(inside.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    mask = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(small_l, small_r, None)
    magnitude = _gradient(small_l)
    keep = mask & (magnitude >= TEXTURE_GRADIENT) & np.isfinite(flow[..., 1])
    if keep.sum() < 50:
        return None
    ys, xs = np.nonzero(keep)
    step = max(1, xs.size // 20000)  # 20k points pin three coefficients; more only costs time
    xs, ys = xs[::step].astype(np.float64), ys[::step].astype(np.float64)
    v = flow[ys.astype(int), xs.astype(int), 1].astype(np.float64)
    A = np.stack([np.ones_like(xs), xs, ys], axis=1)
    inliers = np.ones(v.size, bool)
    coeffs = np.zeros(3)
    # Trimmed least squares: occlusions and mismatches give large vertical flow at a few pixels.
    for _ in range(4):
        coeffs, *_ = np.linalg.lstsq(A[inliers], v[inliers], rcond=None)
        residual = np.abs(A @ coeffs - v)
        inliers = residual <= max(float(np.percentile(residual, 70)), 1e-6)
    sw, sh = size
    corners = np.array([[1, 0, 0], [1, sw - 1, 0], [1, 0, sh - 1], [1, sw - 1, sh - 1]], np.float64) @ coeffs
    return float(np.abs(corners).max() / (sw / w))


def _gradient(grey: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude in grey levels per px (the 3x3 kernels sum to 8 x the slope)."""
    g = grey.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.hypot(gx, gy)


def _texture(grey_l: np.ndarray, inside: np.ndarray) -> tuple[float | None, float | None]:
    h, w = grey_l.shape
    scale = min(1.0, WORK_SIDE / max(h, w))
    size = (max(MIN_SIDE, round(w * scale)), max(MIN_SIDE, round(h * scale)))
    small = cv2.resize(grey_l, size, interpolation=cv2.INTER_AREA) if scale < 1 else grey_l
    mask = cv2.resize(inside.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    # The black fill's edge is steep but is not the photograph's texture.
    mask = cv2.erode(mask, np.ones((5, 5), np.uint8)) > 0
    if not mask.any():
        return None, None
    magnitude = _gradient(small)[mask]
    return float(np.median(magnitude)), float((magnitude >= TEXTURE_GRADIENT).mean())


def measure_card(
    left: np.ndarray,
    right: np.ndarray,
    disp_left: np.ndarray,
    disp_right: np.ndarray | None,
    confidence: np.ndarray | None,
    metrics_by_stage: Mapping[str, Mapping[str, Any]] | None = None,
) -> GradeMeasurements:
    """Measure a rectified pair and its disparity for grading (units in :class:`GradeMeasurements`).

    ``left``, ``right``: uint8 rectified views, ``(H, W)`` or ``(H, W, 3)`` RGB, the same shape,
    at least 16 px a side. ``disp_left``, ``disp_right``, ``confidence``: ``(H, W)`` float maps in
    the views' pixels (NaN / inf = no disparity there); ``disp_right`` and ``confidence`` may be
    ``None`` (their measurements are then missing, with a note). ``metrics_by_stage``:
    ``{"filter": {...}, "rectify": {...}, "disparity": {...}}``, the stages' record metrics; a
    missing stage leaves its measurements missing, with a note.

    Raises :class:`InvalidInputError` on mismatched shapes, wrong dtypes or shapes, and
    :class:`ImageTooSmallError` for views under 16 px a side. Identical views are a valid
    measurement (zero disparity range); an all-NaN map gives coverage 0 and no range.
    """
    left = _check_view(left, "left")
    right = _check_view(right, "right")
    if left.shape[:2] != right.shape[:2]:
        raise InvalidInputError(f"left {left.shape[:2]} and right {right.shape[:2]} differ in size")
    shape = left.shape[:2]
    d_left = _check_map(disp_left, "disp_left", shape)
    d_right = None if disp_right is None else _check_map(disp_right, "disp_right", shape)
    conf = None if confidence is None else _check_map(confidence, "confidence", shape)
    stages = metrics_by_stage or {}
    notes: dict[str, str] = {}
    values: dict[str, Any] = {}

    filter_metrics = stages.get("filter") or {}
    values["good_match_fraction"] = _finite_or_none(filter_metrics.get("good_match_fraction"))
    if values["good_match_fraction"] is None:
        notes["good_match_fraction"] = "no filter metrics" if not filter_metrics else "not in the filter metrics"
    values.update(_rectify_values(stages.get("rectify") or {}, notes))

    grey_l, grey_r = to_grey(np.ascontiguousarray(left)), to_grey(np.ascontiguousarray(right))
    inside_l, inside_r = _photograph(left), _photograph(right)
    if not inside_l.any():  # an all-black view: no fill to tell apart, measure everything
        inside_l = np.ones(shape, bool)
        inside_r = np.ones(shape, bool)
    h, w = shape

    values["row_misalignment_px"] = _row_misalignment(grey_l, grey_r, inside_l)
    if values["row_misalignment_px"] is None:
        notes["row_misalignment_px"] = "too few textured pixels to follow rows"
    values["texture_gradient"], values["textured_fraction"] = _texture(grey_l, inside_l)
    if values["texture_gradient"] is None:
        notes["texture_gradient"] = notes["textured_fraction"] = "the photograph is too small after erosion"

    # A disparity beyond the view's width cannot be a match: counted as not covered, like NaN.
    finite = np.isfinite(d_left) & (np.abs(np.nan_to_num(d_left, nan=0.0, posinf=0.0, neginf=0.0)) <= w)
    covered = finite & inside_l
    values["coverage"] = float(covered.sum() / inside_l.sum())

    xs = np.arange(w, dtype=np.float32)[None, :] - np.where(finite, d_left, 0.0)
    target = np.rint(xs).astype(np.int64)
    on_right = covered & (target >= 0) & (target < w)
    rows = np.broadcast_to(np.arange(h)[:, None], shape)
    target_c = np.clip(target, 0, w - 1)
    on_right &= inside_r[rows, target_c]

    if d_right is None:
        values["lr_consistency"] = None
        notes["lr_consistency"] = "no right disparity map"
    elif not on_right.any():
        values["lr_consistency"] = None
        notes["lr_consistency"] = "no covered pixel matches inside the right view"
    else:
        other = d_right[rows, target_c]
        agree = on_right & np.isfinite(other) & (np.abs(d_left - np.where(np.isfinite(other), other, 0)) <= CONSISTENCY_PX)
        values["lr_consistency"] = float(agree.sum() / on_right.sum())

    if conf is None:
        values["confident_fraction"] = None
        notes["confident_fraction"] = "no confidence map"
    else:
        trusted = np.nan_to_num(conf, nan=0.0, posinf=0.0, neginf=0.0) >= 0.5
        values["confident_fraction"] = float(trusted[inside_l].mean())

    if covered.any():
        p5, p95 = np.percentile(d_left[covered], [5, 95])
        values["disparity_range_px"] = float(p95 - p5)
        values["disparity_range_rel"] = float((p95 - p5) / w)
    else:
        values["disparity_range_px"] = values["disparity_range_rel"] = None
        notes["disparity_range_px"] = notes["disparity_range_rel"] = "no finite disparity on the photograph"

    values["photometric_error"], values["photometric_error_rel"] = None, None
    if on_right.sum() < 16:
        notes["photometric_error"] = notes["photometric_error_rel"] = "too few covered pixels match inside the right view"
    else:
        grid_y, grid_x = np.mgrid[0:h, 0:w].astype(np.float32)
        map_x = np.where(finite, grid_x - d_left, -1.0).astype(np.float32)
        warped = cv2.remap(grey_r, map_x, grid_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        a = grey_l[on_right].astype(np.float64)
        b = warped[on_right].astype(np.float64)
        difference = a - b
        values["photometric_error"] = float(np.mean(np.abs(difference - np.median(difference))))
        spread_a, spread_b = np.mean(np.abs(a - a.mean())), np.mean(np.abs(b - b.mean()))
        if min(spread_a, spread_b) < 0.5:  # a flat view: a normalised difference means nothing
            notes["photometric_error_rel"] = "a view has no contrast where the disparity matches"
        else:
            values["photometric_error_rel"] = float(
                np.mean(np.abs((a - a.mean()) / spread_a - (b - b.mean()) / spread_b)) / math.sqrt(2.0))

    return GradeMeasurements(**values, notes=tuple(sorted(notes.items())))


# --------------------------------------------------------------------------------- thresholds


@dataclass(frozen=True)
class Threshold:
    """One measurement's rule. ``direction`` ``above``: values above ``some`` / ``failure`` are
    artifacts (``>``); ``below``: values under them are (``<``). A ``None`` level is not used."""

    direction: Direction
    some: float | None
    failure: float | None

    def level(self, value: float) -> int:
        """0 few, 1 some, 2 failure."""
        beyond = (lambda t: value > t) if self.direction == "above" else (lambda t: value < t)
        if self.failure is not None and beyond(self.failure):
            return 2
        if self.some is not None and beyond(self.some):
            return 1
        return 0


@dataclass(frozen=True)
class _Rule:
    """How a measurement reads in words, and how its distance to a threshold is scaled."""

    direction: Direction
    scale: Literal["ratio", "complement", "excess", "flag"]
    words: str  # format with {v} (the value formatted by ``unit``)
    unit: Literal["px", "deg", "ratio", "percent", "percent1", "number", "flag"]


_RULES: dict[str, _Rule] = {
    "good_match_fraction": _Rule("below", "ratio", "only {v} of the keypoints match between the halves", "percent1"),
    "dy_p95_px": _Rule("above", "ratio", "rectified matches still differ by {v} in height (95th percentile)", "px"),
    "shear_deg": _Rule("above", "ratio", "rectification sheared {v}", "deg"),
    "aspect_change": _Rule("above", "excess", "rectification changed the aspect ratio by x{v}", "ratio"),
    "rotation_deg": _Rule("above", "ratio", "rectification turned a view by {v}", "deg"),
    "kept_fraction": _Rule("below", "complement", "rectification kept only {v} of a view", "percent"),
    "swapped": _Rule("above", "flag", "eyes swapped on the card (the halves were exchanged: check the depth is not reversed)", "flag"),
    "row_misalignment_px": _Rule("above", "ratio", "rows of the two views are misaligned by {v}", "px"),
    "coverage": _Rule("below", "complement", "disparity covers {v} of the view", "percent"),
    "lr_consistency": _Rule("below", "complement", "left and right disparities agree on only {v} of the pixels", "percent"),
    "confident_fraction": _Rule("below", "complement", "only {v} of the disparities are confident", "percent"),
    "disparity_range_rel": _Rule("below", "ratio", "disparity spans only {range_px} ({v} of the width): little depth to see", "percent1"),
    "textured_fraction": _Rule("below", "ratio", "low texture: only {v} of the view is textured", "percent"),
    "photometric_error_rel": _Rule("above", "ratio", "the right view warped by the disparity misses the left by {grey} on average, {v} of the difference between unrelated images", "number"),
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
    show = lambda value, text: "?" if value is None else text.format(value)
    return {"range_px": show(m.disparity_range_px, "{:.1f} px"), "grey": show(m.photometric_error, "{:.1f} grey levels")}


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

    Defaults, and why (measured figures from this module's tests and ``DESIGN.md``):

    * ``good_match_fraction``: true pairs match 20-34 % of keypoints, unrelated images 0.25-0.45 %,
      the filter culls below 0.5 % and asks people between 0.5 and 1.5 %: under 3 % a pair is
      weakly related (some), under 1 % it is barely a pair (failure).
    * ``dy_p95_px``: rectification refuses a p95 above 2 px (``RectifyParams.max_dy_p95``) and
      calls a pair rectified under 1 px: 1.5 px is visible vertical parallax (some), 3 px makes
      fusion hard (failure; reachable when rectification's own limit is loosened).
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
      read 0.08-0.14 px, the Motorcycle pair with its right view 6 px down reads 6.0 px, and
      unrectified antique pairs 1-10 px: 2 px is visible vertical parallax (some), 4 px strains
      fusion (failure).
    * ``coverage``: the default backend covers 100 %, StereoSGBM 82-86 %: under 80 % holes show
      (some), under 50 % the depth map is mostly missing (failure).
    * ``lr_consistency``: the default backend's maps agree on 84-96 % of Middlebury pairs and
      70-93 % of antique ones, 14 % of unrelated images: under 60 % the maps disagree widely
      (some), under 30 % they are noise (failure).
    * ``confident_fraction``: Middlebury 68-78 %, antique pairs 29-71 %, unrelated images 2 %;
      the disparity stage flags ``low_confidence`` under 20 %: 30 % some, 15 % failure.
    * ``disparity_range_rel``: p95 - p5 of the disparity over the width. Motorcycle spans ~6 %;
      antique cards of distant scenes ~1 %. Under 0.5 % (3.5 px on a 700 px view) the depth map
      is nearly flat (some); under 0.15 % (about 1 px) there is no depth to see (failure: the
      curators' "All-Blue").
    * ``textured_fraction``: share of the view steeper than 3 grey levels / px at 512 px. Real
      photographs measure 36-87 % (Middlebury and antique pairs); under 15 % matching is
      unreliable (some), under 4 % the view is nearly blank (failure).
    * ``photometric_error_rel``: Middlebury pairs 0.06-0.10, antique pairs (different prints,
      residual misalignment) 0.31-0.44, Motorcycle with the right view 6 px down 0.50,
      unrelated images 0.93: above 0.5 the disparity does not explain the pair (some), above
      0.75 it hardly relates the views (failure).
    """

    good_match_fraction: Threshold = Threshold("below", 0.03, 0.01)
    dy_p95_px: Threshold = Threshold("above", 1.5, 3.0)
    shear_deg: Threshold = Threshold("above", 3.0, 8.0)
    aspect_change: Threshold = Threshold("above", 1.15, 1.35)
    rotation_deg: Threshold = Threshold("above", 4.0, 9.0)
    kept_fraction: Threshold = Threshold("below", 0.85, 0.6)
    swapped: Threshold = Threshold("above", 0.5, None)
    row_misalignment_px: Threshold = Threshold("above", 2.0, 4.0)
    coverage: Threshold = Threshold("below", 0.8, 0.5)
    lr_consistency: Threshold = Threshold("below", 0.6, 0.3)
    confident_fraction: Threshold = Threshold("below", 0.3, 0.15)
    disparity_range_rel: Threshold = Threshold("below", 0.005, 0.0015)
    textured_fraction: Threshold = Threshold("below", 0.15, 0.04)
    photometric_error_rel: Threshold = Threshold("above", 0.5, 0.75)

    def __post_init__(self) -> None:
        for name, spec in _RULES.items():
            rule: Threshold = getattr(self, name)
            if not isinstance(rule, Threshold):
                raise InvalidInputError(f"{name}: expected a Threshold, got {type(rule).__name__}")
            if rule.direction != spec.direction:
                raise InvalidInputError(
                    f"{name}: direction must be {spec.direction!r} (what the measurement means), "
                    f"got {rule.direction!r}")
            for level in ("some", "failure"):
                value = getattr(rule, level)
                if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                          or not math.isfinite(value)):
                    raise InvalidInputError(f"{name}.{level}: expected a finite number or null, got {value!r}")
            if rule.some is not None and rule.failure is not None:
                ordered = rule.failure >= rule.some if rule.direction == "above" else rule.failure <= rule.some
                if not ordered:
                    raise InvalidInputError(
                        f"{name}: the failure threshold {rule.failure} must be beyond the some threshold "
                        f"{rule.some} ({rule.direction})")

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """``{measurement: {"direction", "some", "failure"}}`` (JSON-safe)."""
        return {name: {"direction": t.direction, "some": t.some, "failure": t.failure}
                for name, t in ((n, getattr(self, n)) for n in _RULES)}

    @classmethod
    def from_dict(cls, document: Mapping[str, Any]) -> GradeThresholds:
        """Read :meth:`to_dict` output. Measurements it leaves out keep their defaults; an unknown
        measurement, a wrong direction or a non-numeric threshold raises :class:`InvalidInputError`."""
        if not isinstance(document, Mapping):
            raise InvalidInputError(f"Expected a mapping of thresholds, got {type(document).__name__}")
        unknown = sorted(set(document) - set(_RULES))
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


# ---------------------------------------------------------------------------------------- grade


@dataclass(frozen=True)
class GradeResult:
    """``grade`` few / some / failure; ``reasons`` in words, the deciding ones first, then the
    lesser ones, then notes on what was not measured; ``deciding``: the measurements at the
    grade's level (empty for few); ``uncertainty`` in [0, 1] (see :func:`grade`); ``levels``:
    each measured rule's level (0 few, 1 some, 2 failure)."""

    grade: Grade
    reasons: list[str]
    uncertainty: float
    deciding: list[str]
    levels: dict[str, int]
    notes: list[str]

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _distance(name: str, value: float, threshold: float) -> float:
    """Log-ratio distance of a value from a threshold, on the scale the measurement lives on."""
    scale = _RULES[name].scale
    if scale == "flag":
        return math.inf  # a flag is set or not: never "near" its threshold
    if scale == "complement":  # fractions near 1: compare what is missing (5 % vs 20 % missing)
        value, threshold = 1.0 - value, 1.0 - threshold
    elif scale == "excess":  # ratios >= 1: compare the excess over 1
        value, threshold = value - 1.0, threshold - 1.0
    tiny = 1e-9
    return abs(math.log(max(value, tiny) / max(threshold, tiny)))


def grade(measurements: GradeMeasurements | Mapping[str, Any], thresholds: GradeThresholds = GradeThresholds()) -> GradeResult:
    """Grade a card: the worst level any measured rule reaches (few < some < failure).

    A rule whose measurement is missing is skipped, with a note. ``uncertainty`` is
    ``max(0, 1 - d / ln 4)`` where ``d`` is the smallest log-ratio distance
    ``|ln(value / threshold)|`` between a measurement and a threshold *that matters*: one whose
    crossing, every other measurement staying put, would change the grade (for a few card every
    first threshold; for a failure decided by two measurements none). Fractions near 1 (coverage,
    consistency, confidence, kept area) compare what is missing, ``1 - value``; the aspect
    change compares its excess over 1; flags are never near. 1 = a measurement sits on such a
    threshold, 0 = every one is at least a factor of 4 away.
    """
    m = GradeMeasurements.from_dict(measurements) if not isinstance(measurements, GradeMeasurements) else measurements
    levels: dict[str, int] = {}
    values: dict[str, float] = {}
    notes: list[str] = []
    for name in _RULES:
        raw = getattr(m, name)
        if raw is None:
            why = m.note_for(name) or "not measured"
            notes.append(f"note: {name} not graded ({why})")
            continue
        value = float(raw)
        values[name] = value
        levels[name] = getattr(thresholds, name).level(value)
    worst = max(levels.values(), default=0)
    deciding = [name for name, level in levels.items() if level == worst] if worst > 0 else []

    reasons: list[str] = []
    for level in (2, 1):
        for name, reached in levels.items():
            if reached != level:
                continue
            rule, threshold = _RULES[name], getattr(thresholds, name)
            limit = threshold.failure if level == 2 else threshold.some
            text = rule.words.format(v=_format(values[name], rule.unit, limit), **_context(m))
            if rule.unit != "flag":
                op = ">" if rule.direction == "above" else "<"
                text += f" ({op} {_threshold_text(limit, rule.unit)})"
            reasons.append(f"{GRADES[level]}: {text}")
    if worst == 0:
        reasons.append(f"few: every measurement within thresholds ({len(levels)} of {len(_RULES)} measured)")

    nearest = math.inf
    for name, level in levels.items():
        threshold = getattr(thresholds, name)
        others = max((lv for other, lv in levels.items() if other != name), default=0)
        for limit in (threshold.some, threshold.failure):
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
            if max(others, across) != worst:
                nearest = min(nearest, _distance(name, values[name], limit))
    uncertainty = 0.0 if not math.isfinite(nearest) else max(0.0, 1.0 - nearest / UNCERTAINTY_SPAN)
    return GradeResult(grade=GRADES[worst], reasons=reasons + notes, uncertainty=round(uncertainty, 4),
                       deciding=deciding, levels=levels, notes=notes)


# ------------------------------------------------------------------------------------ fitting


def agreement(truth: Sequence[int], predicted: Sequence[int]) -> dict[str, Any]:
    """Confusion matrix (rows = curator label, columns = automatic grade, order few/some/failure),
    accuracy, Cohen's kappa, macro-F1 and per-class precision / recall / support. Labels and
    grades are indices into :data:`GRADES`. Undefined figures (no such class) are ``None``."""
    k = len(GRADES)
    matrix = np.zeros((k, k), np.int64)
    np.add.at(matrix, (np.asarray(truth, np.int64), np.asarray(predicted, np.int64)), 1)
    n = int(matrix.sum())
    out: dict[str, Any] = {"labels": n, "order": list(GRADES), "confusion": matrix.tolist(),
                           "accuracy": None, "cohen_kappa": None, "macro_f1": None, "per_class": {}}
    if n == 0:
        return out
    rows, columns = matrix.sum(1), matrix.sum(0)
    observed = float(np.trace(matrix)) / n
    expected = float(rows @ columns) / (n * n)
    out["accuracy"] = round(observed, 4)
    # kappa is undefined when chance agreement is total (one class on both sides).
    out["cohen_kappa"] = round((observed - expected) / (1 - expected), 4) if expected < 1 else None
    out["macro_f1"] = round(_macro_f1(matrix), 4)
    for i, name in enumerate(GRADES):
        out["per_class"][name] = {
            "precision": round(int(matrix[i, i]) / int(columns[i]), 4) if columns[i] else None,
            "recall": round(int(matrix[i, i]) / int(rows[i]), 4) if rows[i] else None,
            "support": int(rows[i]),
        }
    return out


def _macro_f1(matrix: np.ndarray) -> float:
    """Mean F1 over the classes the curators used (a class nobody labelled has no recall)."""
    scores = []
    for i in range(matrix.shape[0]):
        support, predicted, hit = matrix[i].sum(), matrix[:, i].sum(), matrix[i, i]
        if support == 0:
            continue
        scores.append(2.0 * hit / (support + predicted))
    return float(np.mean(scores)) if scores else 0.0


def _f1_of(truth: np.ndarray, predicted: np.ndarray) -> float:
    matrix = np.zeros((3, 3), np.int64)
    np.add.at(matrix, (truth, predicted), 1)
    return _macro_f1(matrix)


@dataclass(frozen=True)
class FitReport:
    """Thresholds fitted to all labels, and how well fitted thresholds agree with curators.

    ``held_out``: :func:`agreement` pooled over the k held-out folds, each predicted by thresholds
    fitted on the other folds only (so every label is predicted exactly once, by thresholds not
    fitted on it). ``baseline``: the ``base`` thresholds on all labels. ``training``: the fitted
    thresholds on the labels they were fitted on (optimistic; for comparison only).
    ``changed``: the thresholds that moved from ``base``, in words."""

    thresholds: GradeThresholds
    held_out: dict[str, Any]
    baseline: dict[str, Any]
    training: dict[str, Any]
    labels: int
    folds: int
    seed: int
    changed: list[str]
    objective: str = "macro_f1"

    def as_dict(self) -> dict[str, Any]:
        return {"thresholds": self.thresholds.to_dict(), "held_out": self.held_out, "baseline": self.baseline,
                "training": self.training, "labels": self.labels, "folds": self.folds, "seed": self.seed,
                "changed": list(self.changed), "objective": self.objective}


def _matrix_of(rows: Sequence[GradeMeasurements]) -> np.ndarray:
    """(N, rules) float values, NaN where missing (a missing value never raises the grade)."""
    out = np.full((len(rows), len(_RULES)), np.nan)
    for i, m in enumerate(rows):
        for j, name in enumerate(_RULES):
            value = getattr(m, name)
            if value is not None:
                out[i, j] = float(value)
    return out


def _levels(column: np.ndarray, threshold: Threshold) -> np.ndarray:
    """Vectorised :meth:`Threshold.level`; NaN is level 0."""
    level = np.zeros(column.shape, np.int64)
    with np.errstate(invalid="ignore"):
        for value, limit in ((1, threshold.some), (2, threshold.failure)):
            if limit is None:
                continue
            beyond = column > limit if threshold.direction == "above" else column < limit
            level = np.where(beyond, np.maximum(level, value), level)
    return level


def _predict(values: np.ndarray, thresholds: GradeThresholds) -> np.ndarray:
    if values.shape[0] == 0:
        return np.zeros(0, np.int64)
    return np.max(np.stack([_levels(values[:, j], getattr(thresholds, name))
                            for j, name in enumerate(_RULES)], axis=1), axis=1)


def _candidates(column: np.ndarray, name: str) -> list[float | None]:
    """Thresholds to try: None (rule level off), and midpoints between the distinct values at the
    column's 2nd..98th percentiles (25 of them), so a threshold never sits on a labelled value."""
    if _RULES[name].scale == "flag":
        return [None, 0.5]
    finite = column[np.isfinite(column)]
    if finite.size == 0:
        return [None]
    distinct = np.unique(finite)
    if distinct.size == 1:
        return [None, float(distinct[0])]
    midpoints = (distinct[:-1] + distinct[1:]) / 2
    picks = np.unique(np.percentile(midpoints, np.linspace(2, 98, 25), method="nearest"))
    return [None, *(float(p) for p in picks)]


def _fit(values: np.ndarray, truth: np.ndarray, base: GradeThresholds, sweeps: int = 6) -> GradeThresholds:
    """Coordinate descent from ``base``: for each rule in turn, for its some and failure levels,
    take the candidate (or None) with the best macro-F1 given every other threshold; keep the
    current one unless another is strictly better; stop when a sweep changes nothing."""
    names = list(_RULES)
    current = {name: getattr(base, name) for name in names}
    levels = np.stack([_levels(values[:, j], current[name]) for j, name in enumerate(names)], axis=1)
    best = _f1_of(truth, levels.max(axis=1))
    candidates = {name: _candidates(values[:, j], name) for j, name in enumerate(names)}
    for _ in range(sweeps):
        improved = False
        for j, name in enumerate(names):
            others = np.delete(levels, j, axis=1).max(axis=1) if len(names) > 1 else np.zeros(len(truth), np.int64)
            for level_name in ("some", "failure"):
                rule = current[name]
                for candidate in candidates[name]:
                    trial = replace(rule, **{level_name: candidate})
                    if trial.some is not None and trial.failure is not None and (
                        (trial.failure < trial.some) if trial.direction == "above" else (trial.failure > trial.some)
                    ):
                        continue  # a failure threshold short of the some threshold
                    column = _levels(values[:, j], trial)
                    score = _f1_of(truth, np.maximum(others, column))
                    if score > best + 1e-12:
                        best, rule, improved = score, trial, True
                        levels[:, j] = column
                current[name] = rule
        if not improved:
            break
    return GradeThresholds(**current)


def _stratified_folds(truth: np.ndarray, k: int, rng: np.random.Generator) -> list[np.ndarray]:
    folds: list[list[int]] = [[] for _ in range(k)]
    offset = 0
    for cls in np.unique(truth):
        members = rng.permutation(np.flatnonzero(truth == cls))
        for n, i in enumerate(members):
            folds[(n + offset) % k].append(int(i))
        offset += len(members)
    return [np.array(sorted(f), np.int64) for f in folds]


def _changes(base: GradeThresholds, fitted: GradeThresholds) -> list[str]:
    out = []
    for name in _RULES:
        before, after = getattr(base, name), getattr(fitted, name)
        for level in ("some", "failure"):
            a, b = getattr(before, level), getattr(after, level)
            if a != b:
                show = lambda t: "off" if t is None else f"{t:.6g}"
                out.append(f"{name} {level}: {show(a)} -> {show(b)}")
    return out


def fit_thresholds(
    rows: Sequence[tuple[GradeMeasurements | Mapping[str, Any], str]],
    base: GradeThresholds = GradeThresholds(),
    folds: int = 5,
    seed: int = 0,
) -> FitReport:
    """Fit the thresholds to curator labels and report held-out agreement.

    ``rows``: (measurements, curator grade in few / some / failure). The fit is coordinate descent
    from ``base`` over candidate thresholds at the measurements' quantiles (or a level switched
    off), maximising macro-F1, so the result is still a readable set of thresholds. Agreement is
    estimated by stratified ``folds``-fold cross-validation: thresholds are refitted on k-1 folds
    and grade the fold left out; the pooled confusion matrix covers every label exactly once.

    Raises :class:`NotEnoughLabelsError` for fewer than 10 labels, a single class, or fewer
    labels than folds; :class:`InvalidInputError` for an unknown grade or ``folds < 2``.
    """
    if folds < 2:
        raise InvalidInputError(f"Expected folds >= 2, got {folds}")
    index = {g: i for i, g in enumerate(GRADES)}
    measured: list[GradeMeasurements] = []
    truth_list: list[int] = []
    for position, row in enumerate(rows):
        try:
            values, label = row
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"row {position}: expected (measurements, label), got {row!r}") from exc
        if label not in index:
            raise InvalidInputError(f"row {position}: unknown grade {label!r}; expected one of {', '.join(GRADES)}")
        measured.append(GradeMeasurements.from_dict(values))
        truth_list.append(index[label])
    n = len(measured)
    needed = max(MIN_LABELS, folds)
    if n < needed:
        raise NotEnoughLabelsError(
            f"{n} curator labels; at least {needed} are needed to fit and cross-validate ({needed - n} more)")
    truth = np.array(truth_list, np.int64)
    classes = sorted({GRADES[t] for t in truth_list})
    if len(classes) < 2:
        raise NotEnoughLabelsError(
            f"all {n} curator labels are {classes[0]!r}: grade at least one card of another class "
            "(few, some, failure) before fitting")
    values = _matrix_of(measured)
    rng = np.random.default_rng(seed)
    predicted = np.full(n, -1, np.int64)
    for test in _stratified_folds(truth, folds, rng):
        if test.size == 0:
            continue
        train = np.setdiff1d(np.arange(n), test)
        fold_thresholds = _fit(values[train], truth[train], base)
        predicted[test] = _predict(values[test], fold_thresholds)
    fitted = _fit(values, truth, base)
    return FitReport(
        thresholds=fitted,
        held_out=agreement(truth, predicted),
        baseline=agreement(truth, _predict(values, base)),
        training=agreement(truth, _predict(values, fitted)),
        labels=n, folds=folds, seed=seed, changed=_changes(base, fitted),
    )
