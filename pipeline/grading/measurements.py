"""What the grade is computed from: :func:`measure_card` turns a rectified pair, its disparity maps
and the earlier stages' metrics into :class:`GradeMeasurements` (units in its docstring).

Conventions as in :mod:`pipeline.disparity`: a left pixel ``(x, y)`` is seen in the right view at
``x_right = x_left - d_left``; a right pixel at ``x_left = x_right + d_right``. Views are uint8
``(H, W)`` grey or ``(H, W, 3)`` RGB; pixels that are 0 in every channel of a view are the
warp's black fill, outside the photograph. The disparity maps must have the views' shape.

Units do not change with the scan's size: a measurement in pixels is given at a view
:data:`REFERENCE_SIDE` px on its longer side (the measurement in the stored view's own pixels x
``REFERENCE_SIDE / longer side``, i.e. the same fraction of the view whatever the scan's
resolution), and texture and row alignment are measured on copies resampled to exactly
:data:`WORK_SIDE` px (down or up), so that a card scanned at 0.5x or 4x measures as at 1x.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import cv2
import numpy as np

from ..disparity import ImageTooSmallError, percentiles_from_counts
from ..errors import InvalidInputError
from ..io import to_grey
from ..rectify import photograph_mask
from . import scene_checks

__all__ = ["MEASUREMENT_NAMES", "TEXT_FIELDS", "GradeMeasurements", "finite_or_none", "measure_card"]

MIN_SIDE = 16  # px: as the disparity stage; smaller views have nothing to measure
# px: the longer side of the view at which every pixel measurement is stated. The filter's SIFT
# side (FilterParams.max_side), where the matches that rectification reuses are found: a p95 |dy|
# of 2 px here is rectification's own refusal (RectifyParams.max_dy_p95) on any scan over 600 px.
REFERENCE_SIDE = 600
WORK_SIDE = 512  # px: texture and row alignment are measured on copies resampled to this longer side
TEXTURE_GRADIENT = 3.0  # grey levels / px at WORK_SIDE: a pixel at least this steep counts as textured
CONSISTENCY_PX = 1.0  # left-right check tolerance (px), as the disparity stage's default


@dataclass(frozen=True)
class GradeMeasurements:
    """What the grade is computed from. ``None`` = not measured (``notes`` says why).

    From the filter stage:

    * ``good_match_fraction``: SIFT ratio-test matches / keypoints between the halves (0..1).

    From the rectify stage (the worse of the two views where it measures both):

    * ``dy_p95_px``: px at the resolution the matches were found at (the filter matches every
      half resampled to 600 px, :data:`REFERENCE_SIDE`, whatever the scan's size), but never finer
      than a pixel of the scan (a scan whose halves are under 600 px: its own px), 95th percentile
      of inlier ``|y_l - y_r|`` after rectification: the figure rectification's own 2 px limit
      applies to (the rectify metrics' ``dy_p95_match``; a record without it: the stored view's
      ``dy_p95`` x ``REFERENCE_SIDE`` / the view's longer side).
    * ``shear_deg``: deg, ``90 - midline_angle``: how far the images of the midlines are from
      perpendicular (0 = no shear).
    * ``aspect_change``: ratio >= 1, change of the midline length ratio (1 = none).
    * ``rotation_deg``: deg, ``|in-plane rotation|`` of a view.
    * ``kept_fraction``: smallest share (0..1) of a view's warped area inside the output.
    * ``swapped``: the eyes were swapped on the card (the halves were exchanged).

    Measured here from the rectified views and the disparity maps:

    * ``row_misalignment_px``: px at :data:`REFERENCE_SIDE`, largest ``|v|`` at the four corners
      of a robust plane ``v = c0 + c1 x + c2 y`` fitted to the vertical component of DIS optical
      flow from the left to the right view over textured pixels (views resampled to
      ``WORK_SIDE``): what a viewer sees as vertical parallax, whatever the rectification reported.
    * ``coverage``: share (0..1) of the left view's photograph (non-black pixels) with a finite
      left disparity (NaN, inf and ``|d|`` above the view width count as none).
    * ``lr_consistency``: share (0..1) of covered left pixels whose match ``x - d_L`` lies inside
      the right view with ``|d_L(x) - d_R(x - d_L(x))| <= 1 px`` (``d_R`` at the nearest pixel).
    * ``confident_fraction``: share (0..1) of the photograph with confidence >= 0.5.
    * ``disparity_range_px``: px, p95 - p5 of the finite left disparities on the photograph;
      ``disparity_range_rel`` is the same over the view width (0.05 = 5 % of the width).
    * ``texture_gradient``: grey levels per px, median Sobel gradient magnitude of the grey left
      view resampled to ``WORK_SIDE``; ``textured_fraction``: share (0..1) of the photograph at least
      ``TEXTURE_GRADIENT`` steep there.
    * ``photometric_error``: grey levels (0..255), mean ``|L(x, y) - R(x - d_L, y)|`` over covered
      pixels whose match falls on the right photograph, after removing the median brightness
      difference between the views. ``photometric_error_rel``: the same after normalising each
      view to zero mean and unit mean absolute deviation over those pixels, divided by sqrt(2):
      0 = the warped right view reproduces the left, about 1 = as different as two unrelated
      images (for roughly Gaussian intensities); gain and offset between the prints cancel.

    What the depth map says about the scene and what the crop holds
    (:mod:`pipeline.grading.scene_checks`, definitions there):

    * ``depth_order``: dimensionless, -1..1: (median d of the lowest third of rows - median d
      of the highest third) / (p95 - p5 of d); positive = the bottom is nearer, as on most scenes.
    * ``streak_fraction``: share (0..1) of the photograph on row streaks of the disparity.
    * ``sky_near_fraction``: share (0..1) of the upper half that is textureless yet reads nearer
      than the median textured pixel.
    * ``reflection_symmetry``: 0..1, the mirror symmetry (intensity and disparity) of the lower
      part about the horizon row ``reflection_row_px`` (px in the rectified view).
    * ``border_line``: share (0..1) of the crop's ``border_side`` border that a straight steep edge
      with a plain strip outside it runs along (card edge, mount); ``border_strokes``: share
      (0..1) of the most inked border strip that is ink-like strokes beyond the interior's.
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
    depth_order: float | None = None
    streak_fraction: float | None = None
    sky_near_fraction: float | None = None
    reflection_symmetry: float | None = None
    reflection_row_px: float | None = None
    border_line: float | None = None
    border_strokes: float | None = None
    border_side: str | None = None
    notes: tuple[tuple[str, str], ...] = ()  # (measurement, why it is missing)

    def as_dict(self) -> dict[str, Any]:
        """JSON-safe ``{name: float | bool | None}`` (no NaN; notes are not included)."""
        out: dict[str, Any] = {}
        for name in MEASUREMENT_NAMES:
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)):
                out[name] = bool(value)
            elif name in TEXT_FIELDS:
                out[name] = None if value is None else str(value)
            elif value is None or not math.isfinite(float(value)):
                out[name] = None
            else:
                out[name] = round(float(value), 6)
        return out

    def note_for(self, name: str) -> str | None:
        return dict(self.notes).get(name)

    @classmethod
    def from_dict(cls, values: GradeMeasurements | Mapping[str, Any]) -> GradeMeasurements:
        """Read :meth:`as_dict` output (or a grade record's metrics: other keys are ignored).
        Non-numeric or non-finite values become ``None``."""
        if isinstance(values, GradeMeasurements):
            return values
        if not isinstance(values, Mapping):
            raise InvalidInputError(f"Expected a mapping of grade measurements, got {type(values).__name__}")
        kwargs: dict[str, Any] = {}
        for name in MEASUREMENT_NAMES:
            value = values.get(name)
            if name == "swapped":
                kwargs[name] = None if value is None else bool(value)
            elif name in TEXT_FIELDS:
                kwargs[name] = value if isinstance(value, str) else None
            else:
                kwargs[name] = finite_or_none(value)
        return cls(**kwargs)


MEASUREMENT_NAMES: tuple[str, ...] = tuple(f.name for f in fields(GradeMeasurements) if f.name != "notes")
TEXT_FIELDS = frozenset({"border_side"})


def finite_or_none(value: Any) -> float | None:
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


def _check_map(values: Any, name: str, shape: tuple[int, int], disparity: bool = True) -> np.ndarray:
    """A map in the views' pixels. A map computed at a smaller working size (same aspect within
    3 %) is brought to the views' size by nearest-neighbour resampling; a disparity map's values
    are in its own pixels, so they are scaled by the width ratio to become view px."""
    array = np.asarray(values)
    if array.ndim != 2:
        raise InvalidInputError(f"{name}: expected an (H, W) map, got shape {array.shape}")
    if array.dtype.kind not in "fiu":
        raise InvalidInputError(f"{name}: expected a numeric map, got {array.dtype}")
    array = array.astype(np.float32, copy=False)
    if array.shape == shape:
        return array
    (h, w), (mh, mw) = shape, array.shape
    if min(mh, mw) < 2 or abs((mw / mh) / (w / h) - 1.0) > 0.03:
        raise InvalidInputError(
            f"{name}: expected shape {shape} (the views') or the same aspect at another size, got {array.shape}"
        )
    resized = cv2.resize(array, (w, h), interpolation=cv2.INTER_NEAREST)
    return resized * np.float32(w / mw) if disparity else resized


def _grey_difference_median(difference: np.ndarray) -> float:
    """``np.median`` of differences of two uint8 grey levels (whole numbers in -255..255, float64),
    counted in a 511-bin histogram instead of partitioned (the same value: the middle element, or
    the mean of the two middle ones; a third of the time on 500,000 pixels)."""
    counts = np.bincount((difference + 255.0).astype(np.intp), minlength=511)
    return float(percentiles_from_counts(counts, (50.0,))[0]) - 255.0


def _rectify_values(rectify: Mapping[str, Any], notes: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    out["dy_p95_px"] = finite_or_none(rectify.get("dy_p95"))
    angle = finite_or_none(rectify.get("midline_angle"))
    out["shear_deg"] = None if angle is None else abs(90.0 - angle)
    out["aspect_change"] = finite_or_none(rectify.get("aspect_change"))
    rotation = finite_or_none(rectify.get("rotation"))
    out["rotation_deg"] = None if rotation is None else abs(rotation)
    out["kept_fraction"] = finite_or_none(rectify.get("kept_fraction"))
    swapped = rectify.get("swapped")
    out["swapped"] = None if swapped is None else bool(swapped)
    why = "no rectify metrics" if not rectify else "not in the rectify metrics"
    for name, value in out.items():
        if value is None:
            notes[name] = why
    return out


def _work_size(shape: tuple[int, ...]) -> tuple[int, int]:
    """``(width, height)`` of a view of ``shape`` resampled to :data:`WORK_SIDE` on its longer side."""
    h, w = shape[:2]
    scale = WORK_SIDE / max(h, w)
    return max(MIN_SIDE, round(w * scale)), max(MIN_SIDE, round(h * scale))


def _at_work_side(grey: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``grey`` resampled to ``size``: area filter down, bilinear up (a small scan is measured as
    the same print scanned larger, not at its own coarser pixel)."""
    if grey.shape[1::-1] == size:
        return grey
    shrinking = size[0] < grey.shape[1]
    return np.asarray(cv2.resize(grey, size, interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR))


def _row_misalignment(grey_l: np.ndarray, grey_r: np.ndarray, inside: np.ndarray) -> float | None:
    """px at :data:`REFERENCE_SIDE` (see :class:`GradeMeasurements`); None without textured pixels."""
    size = _work_size(grey_l.shape)
    small_l, small_r = _at_work_side(grey_l, size), _at_work_side(grey_r, size)
    mask = cv2.resize(inside.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    mask = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    flow = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(small_l, small_r, None)  # type: ignore[call-overload]
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
    return float(np.abs(corners).max() * REFERENCE_SIDE / max(sw, sh))


def _gradient(grey: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude in grey levels per px (the 3x3 kernels sum to 8 x the slope)."""
    g = grey.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.hypot(gx, gy)


def _texture(grey_l: np.ndarray, inside: np.ndarray) -> tuple[float | None, float | None]:
    size = _work_size(grey_l.shape)
    small = _at_work_side(grey_l, size)
    inside_u8 = cv2.resize(inside.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    # The black fill's edge is steep but is not the photograph's texture.
    mask = np.asarray(cv2.erode(inside_u8, np.ones((5, 5), np.uint8)) > 0)
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
    the views' pixels (NaN / inf = no disparity there; maps computed at a smaller working size of
    the same aspect are resampled to the views' pixels and their disparities scaled to view px);
    ``disp_right`` and ``confidence`` may be
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
    conf = None if confidence is None else _check_map(confidence, "confidence", shape, disparity=False)
    stages = metrics_by_stage or {}
    notes: dict[str, str] = {}
    values: dict[str, Any] = {}

    filter_metrics = stages.get("filter") or {}
    values["good_match_fraction"] = finite_or_none(filter_metrics.get("good_match_fraction"))
    if values["good_match_fraction"] is None:
        notes["good_match_fraction"] = "no filter metrics" if not filter_metrics else "not in the filter metrics"
    rectify_metrics = stages.get("rectify") or {}
    values.update(_rectify_values(rectify_metrics, notes))
    at_matching = finite_or_none(rectify_metrics.get("dy_p95_match"))
    if at_matching is not None:  # px at the matching resolution (the filter's 600 px halves)
        values["dy_p95_px"] = at_matching
    elif values["dy_p95_px"] is not None:  # older records: the stored view's px -> px at REFERENCE_SIDE
        values["dy_p95_px"] *= REFERENCE_SIDE / max(shape)

    grey_l, grey_r = to_grey(np.ascontiguousarray(left)), to_grey(np.ascontiguousarray(right))
    inside_l, inside_r = photograph_mask(left), photograph_mask(right)
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
    # Each pixel's match on the right view as a flat index (a gather with 2-D fancy indices
    # costs twice as much on an 800 px view).
    target_flat = np.clip(target, 0, w - 1) + np.arange(0, h * w, w)[:, None]
    on_right &= inside_r.ravel().take(target_flat)

    if d_right is None:
        values["lr_consistency"] = None
        notes["lr_consistency"] = "no right disparity map"
    elif not on_right.any():
        values["lr_consistency"] = None
        notes["lr_consistency"] = "no covered pixel matches inside the right view"
    else:
        other = np.ascontiguousarray(d_right).ravel().take(target_flat)
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
        grid_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
        map_x = np.where(finite, np.arange(w, dtype=np.float32)[None, :] - d_left, -1.0).astype(np.float32)
        warped = cv2.remap(grey_r, map_x, grid_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        a = grey_l[on_right].astype(np.float64)
        b = warped[on_right].astype(np.float64)
        difference = a - b
        values["photometric_error"] = float(np.mean(np.abs(difference - _grey_difference_median(difference))))
        spread_a, spread_b = np.mean(np.abs(a - a.mean())), np.mean(np.abs(b - b.mean()))
        if min(spread_a, spread_b) < 0.5:  # a flat view: a normalised difference means nothing
            notes["photometric_error_rel"] = "a view has no contrast where the disparity matches"
        else:
            values["photometric_error_rel"] = float(
                np.mean(np.abs((a - a.mean()) / spread_a - (b - b.mean()) / spread_b)) / math.sqrt(2.0)
            )

    values.update(_scene_values(grey_l, d_left, covered, inside_l, notes))
    return GradeMeasurements(**values, notes=tuple(sorted(notes.items())))


def _scene_values(
    grey: np.ndarray, d_left: np.ndarray, covered: np.ndarray, inside: np.ndarray, notes: dict[str, str]
) -> dict[str, Any]:
    """The scene checks (:mod:`.scene_checks`) on the left view and its covered disparities."""
    disp = np.where(covered, d_left, np.nan).astype(np.float32)
    out: dict[str, Any] = {}
    out["depth_order"] = scene_checks.depth_order(disp, covered)
    if out["depth_order"] is None:
        notes["depth_order"] = "under 1 px of disparity range or too few disparities to order"
    out["streak_fraction"] = scene_checks.streak_fraction(disp, covered)
    if out["streak_fraction"] is None:
        notes["streak_fraction"] = "too few disparities to look for streaks"
    out["sky_near_fraction"] = scene_checks.sky_near_fraction(grey, disp, inside)
    if out["sky_near_fraction"] is None:
        notes["sky_near_fraction"] = "too few textured pixels with a disparity to compare with"
    reflection = scene_checks.reflection_symmetry(grey, disp, covered)
    out["reflection_symmetry"] = None if reflection is None else reflection.symmetry
    out["reflection_row_px"] = None if reflection is None else float(reflection.row_px)
    if reflection is None:
        notes["reflection_symmetry"] = "the view is too small or has no disparity"
    border = scene_checks.border_intrusion(grey, inside)
    out["border_line"] = None if border is None else border.line
    out["border_strokes"] = None if border is None else border.strokes
    out["border_side"] = None if border is None else border.side
    if border is None:
        notes["border_line"] = notes["border_strokes"] = "the photograph is too small to have a border strip"
    return out
