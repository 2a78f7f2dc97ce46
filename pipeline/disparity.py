"""Dense disparity for both views of a rectified pair, and depth up to scale.

Conventions (all maps are float32, in pixels, at the input's resolution):

* ``disp_left``: a left-view pixel ``(x, y)`` is seen in the right view at ``x_right = x_left - d_left``.
* ``disp_right``: a right-view pixel ``(x, y)`` is seen in the left view at ``x_left = x_right + d_right``.
  For a scene in front of the cameras both are >= 0 on a correctly rectified pair.
* ``confidence`` in 0..1 from forward-backward (flow) or left-right (stereo) consistency;
  ``confident_fraction`` is the share of pixels with confidence >= 0.5 (consistency error <= 1 px).

Backends (:data:`BACKENDS`):

* ``dis-ultrafast`` / ``dis-fast`` / ``dis-medium``: OpenCV DIS optical flow presets, left->right
  (``d_left = -u``) and right->left (``d_right = u``); full coverage.
* ``deepflow``: OpenCV contrib DeepFlow, same use of the flow; full coverage, about 1 s per direction.
* ``sgbm``: StereoSGBM baseline on the pair as given, search 0..width/8 unless
  ``disparity_range`` is known; pixels it rejects stay NaN (not covered).
* ``keystone`` (the default): residual-misalignment-corrected SGBM with occlusion-aware filling.
  1. DIS (fast preset) flow left->right; a robust least-squares fit of its vertical component
     ``v = c0 + c1 x + c2 y`` measures the residual vertical offset / rotation of the right view.
     When the flow is too poor for the fit (median residual > 1 px), phase correlation's vertical
     shift stands in as a plain offset.
  2. The right view is resampled so that rows align (``R'(x, y) = R(x - c1 (y - cy), y + v(x, y))``;
     the horizontal term undoes the horizontal part of a small rotation about the image centre).
  3. The corrected right view's grey levels are remapped so its histogram matches the left's (a
     global exposure / development difference between the views biases SGBM's intensity cost).
  4. StereoSGBM on the corrected pair for both views (the right view by mirroring), with the search
     range from ``DisparityParams.disparity_range`` when known, else from the flow's percentiles
     widened to the dominant shift found by phase correlation (huge disparities the flow misses).
     Both views are padded by the search range (replicated columns) so that SGBM matches the strip
     it otherwise leaves empty on the reference side; a match that lands outside the other view
     stays empty (then filled as an occlusion).
  5. Left-right check -> confidence; pixels SGBM rejected are filled along their row with the smaller
     (background) of the nearest consistent disparities on either side (occlusions belong to the
     background), a 5x5 median smooths the filled pixels; rows with nothing SGBM kept take the
     flow's disparity. Then every pixel that fails the left-right check (filled or inconsistent)
     takes an image-guided weighted median (quarter resolution on maps of 400 px and more, else
     half). Full coverage, no NaN.
  Tuned on Motorcycle and Tsukuba, held out: Adirondack (both exposures); see docs/BENCHMARKS.md.
  ``disp_right`` is expressed in the corrected right view's pixel grid (within a few px of the
  original's for the residual offsets this corrects).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from .errors import InvalidInputError

__all__ = [
    "BACKENDS",
    "DEFAULT_BACKEND",
    "DisparityParams",
    "DisparityResult",
    "ImageTooSmallError",
    "UnknownBackendError",
    "depth_from_disparity",
    "estimate_disparity",
    "normalised_inverse_depth",
    "resample_512",
]

BACKENDS = ("dis-ultrafast", "dis-fast", "dis-medium", "deepflow", "sgbm", "keystone")
FULL_COVERAGE_BACKENDS = ("dis-ultrafast", "dis-fast", "dis-medium", "deepflow", "keystone")
DEFAULT_BACKEND = "keystone"
MIN_SIDE = 16  # smaller images are refused (DIS and SGBM have nothing to work with)

_DIS_PRESETS = {
    "dis-ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "dis-fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "dis-medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


class UnknownBackendError(InvalidInputError):
    code = "unknown_backend"


class ImageTooSmallError(InvalidInputError):
    code = "image_too_small"


@dataclass(frozen=True)
class DisparityParams:
    """``disparity_range``: (min, max) px measured by rectification, when known; it sets SGBM's
    search range (and skips the flow-based estimate). ``block_size``: SGBM block (odd)."""

    disparity_range: tuple[float, float] | None = None
    block_size: int = 3
    consistency_px: float = 1.0


@dataclass
class DisparityResult:
    disp_left: np.ndarray
    disp_right: np.ndarray
    confidence: np.ndarray
    confident_fraction: float
    seconds: float
    backend: str
    flags: tuple[str, ...] = ()
    vertical_model: tuple[float, float, float] | None = field(default=None)

    @property
    def coverage(self) -> float:
        """Fraction of left pixels with a finite disparity."""
        return float(np.isfinite(self.disp_left).mean())


# ----------------------------------------------------------------------------------------- input
def _to_gray8(image: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise InvalidInputError(f"{name}: expected HxW or HxWx3/4, got shape {a.shape}")
    if a.dtype.kind not in "uif" and a.dtype != np.bool_:
        raise InvalidInputError(f"{name}: unsupported dtype {a.dtype}")
    if a.dtype.kind == "f":
        if not np.isfinite(a).all():
            raise InvalidInputError(f"{name}: contains NaN or infinite values")
        scale = 255.0 if a.max(initial=0.0) <= 1.0 else 1.0
        a = np.clip(a.astype(np.float32) * scale, 0, 255).astype(np.uint8)
    elif a.dtype == np.uint16:
        a = (a.astype(np.uint32) // 257).astype(np.uint8)
    elif a.dtype != np.uint8:
        a = np.clip(a, 0, 255).astype(np.uint8)
    if a.ndim == 3:
        a = cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(a)


def percentiles_from_counts(counts: np.ndarray, percents: tuple[float, ...]) -> np.ndarray:
    """``np.percentile`` (its default linear interpolation, float64, the same values to the bit) of
    the values ``0 .. len(counts) - 1`` held ``counts[v]`` times each: the k-th smallest value is
    the first whose cumulative count exceeds k. For whole-number data in a small range (grey
    levels, their differences), a histogram replaces a partition of every pixel."""
    cumulative = np.cumsum(counts)
    n = int(cumulative[-1]) if cumulative.size else 0
    if n == 0:
        raise InvalidInputError("no pixels to take percentiles of")
    index = (n - 1) * (np.asarray(percents, np.float64) / 100)
    below = np.floor(index).astype(np.int64)
    a = np.searchsorted(cumulative, below, side="right").astype(np.float64)
    b = np.searchsorted(cumulative, np.minimum(below + 1, n - 1), side="right").astype(np.float64)
    t = index - below
    # numpy's own interpolation, both branches: the same rounding as np.percentile
    return np.where(t >= 0.5, b - (b - a) * (1 - t), a + (b - a) * t)


def uint8_percentiles(images: tuple[np.ndarray, ...], percents: tuple[float, ...]) -> np.ndarray:
    """``np.percentile`` of the uint8 ``images``' pixels taken together, to the bit, from one
    256-level histogram (:func:`percentiles_from_counts`). Measured on two 800 x 750 px views:
    1.4 ms instead of 13.6 ms to concatenate and partition them."""
    counts = sum(np.bincount(np.asarray(image, np.uint8).ravel(), minlength=256) for image in images)
    return percentiles_from_counts(np.asarray(counts), percents)


def _prepare(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    L, R = _to_gray8(left, "left"), _to_gray8(right, "right")
    if L.shape != R.shape:
        raise InvalidInputError(f"left {L.shape} and right {R.shape} differ in size")
    if min(L.shape) < MIN_SIDE:
        raise ImageTooSmallError(f"image {L.shape[1]}x{L.shape[0]} is below {MIN_SIDE} px on a side")
    flags: list[str] = []
    # One contrast stretch for both views (keeps them photometrically comparable): rescues very
    # dark or overexposed pairs, leaves normal ones nearly unchanged.
    lo, hi = uint8_percentiles((L, R), (0.5, 99.5))
    if hi - lo < 2:
        flags.append("textureless")
    elif hi - lo < 96:
        scale = 255.0 / float(hi - lo)
        L = cv2.convertScaleAbs(L, alpha=scale, beta=-lo * scale)
        R = cv2.convertScaleAbs(R, alpha=scale, beta=-lo * scale)
        flags.append("contrast_stretched")
    return L, R, tuple(flags)


# ------------------------------------------------------------------------------------------ flow
# Every backend's (left disparity, right disparity, confidence, vertical model or None).
_BackendOutput = tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float, float] | None]


def _flow(backend: str, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if backend == "deepflow":
        # cv2's stubs want a flow array; None (allocate it) is what the binding accepts and means
        return np.asarray(cv2.optflow.createOptFlow_DeepFlow().calc(a, b, None), np.float32)  # type: ignore[call-overload]
    dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[backend])  # type: ignore[attr-defined]  # cv2's stubs lack the factory
    return np.asarray(dis.calc(a, b, None), np.float32)


def _fb_error(fwd: np.ndarray, bwd: np.ndarray) -> np.ndarray:
    """|fwd(p) + bwd(p + fwd(p))| per pixel of fwd's view."""
    h, w = fwd.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    back = cv2.remap(bwd, xs + fwd[..., 0], ys + fwd[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.hypot(fwd[..., 0] + back[..., 0], fwd[..., 1] + back[..., 1])


def _confidence(err: np.ndarray, tol: float) -> np.ndarray:
    err = np.where(np.isfinite(err), err, np.inf)
    return (1.0 / (1.0 + (err / tol) ** 2)).astype(np.float32)


def _flow_backend(backend: str, L: np.ndarray, R: np.ndarray, params: DisparityParams) -> _BackendOutput:
    fwd = _flow(backend, L, R)
    bwd = _flow(backend, R, L)
    conf = _confidence(_fb_error(fwd, bwd), params.consistency_px)
    d_left = np.nan_to_num(-fwd[..., 0], nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    d_right = np.nan_to_num(bwd[..., 0], nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    return d_left, d_right, conf, None


# ------------------------------------------------------------------------------------------ sgbm
def _dominant_shift(L: np.ndarray, R: np.ndarray) -> tuple[float, float] | None:
    """Dominant (disparity, vertical offset) by phase correlation: catches shifts too large for the
    flow pyramid, and the vertical offset when the flow is too poor for a plane fit."""
    h, w = L.shape
    window = cv2.createHanningWindow((w, h), cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(L.astype(np.float32), R.astype(np.float32), window)
    ok = response > 0.1 and np.isfinite(dx) and np.isfinite(dy)
    return (-float(dx), float(dy)) if ok else None


def _search_range(
    params: DisparityParams, rough: np.ndarray | None, width: int, dominant: float | None = None
) -> tuple[int, int]:
    if params.disparity_range is not None:
        lo, hi = (float(v) for v in params.disparity_range)
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
            raise InvalidInputError(f"bad disparity_range {params.disparity_range}")
        lo, hi = lo - 2, hi + 2
    elif rough is not None:
        lo, hi = np.percentile(rough, [0.5, 99.5])
        lo, hi = min(0.0, lo - 4), hi * 1.2 + 8
        if dominant is not None:
            lo, hi = min(lo, dominant - 16), max(hi, dominant + 16)
    else:  # the plain SGBM baseline without a known range: 0 .. width / 8
        lo, hi = 0.0, width / 8
    min_d = int(np.floor(lo))
    num = int(np.ceil(max(hi - min_d, 16) / 16.0)) * 16
    num = max(16, min(num, (width - 1) // 16 * 16))
    return min_d, num


def _sgbm_pair(
    L: np.ndarray, R: np.ndarray, min_d: int, num: int, block: int, pad: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """SGBM for the left view and (mirrored) for the right view; invalid = NaN.

    ``pad``: StereoSGBM never matches the first ``min_d + num`` columns of its reference view (the
    search would leave the other image), so a plain run leaves a strip as wide as the search range
    empty, and filling it from its one neighbour is mostly wrong (measured: 2.7 of the 8.8 points
    of bad-2 on Adirondack). With ``pad`` both views get that many replicated columns on the
    reference side (and ``-min_d`` on the other side for negative disparities), the strip is
    matched for real, and only pixels whose match lands outside the other view are left empty."""
    P1, P2 = 8 * block * block, 32 * block * block  # OpenCV's guidance for one channel
    matcher = cv2.StereoSGBM_create(  # type: ignore[attr-defined]  # cv2's stubs lack the factory
        minDisparity=min_d,
        numDisparities=num,
        blockSize=block,
        P1=P1,
        P2=P2,
        disp12MaxDiff=-1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    before, after = (max(0, min_d + num), max(0, -min_d)) if pad else (0, 0)
    w = L.shape[1]
    cols = np.arange(w, dtype=np.float32)[None, :]
    out = []
    for a, b, mirror in ((L, R, False), (R, L, True)):
        if mirror:
            a, b = np.ascontiguousarray(a[:, ::-1]), np.ascontiguousarray(b[:, ::-1])
        if before or after:
            a = cv2.copyMakeBorder(a, 0, 0, before, after, cv2.BORDER_REPLICATE)
            b = cv2.copyMakeBorder(b, 0, 0, before, after, cv2.BORDER_REPLICATE)
        raw = matcher.compute(a, b)[:, before : before + w]
        d = raw.astype(np.float32) / 16.0
        d[raw < min_d * 16] = np.nan
        if pad:  # a match in the padding is a guess, not a match
            with np.errstate(invalid="ignore"):
                d[(cols - d < 0) | (cols - d > w - 1)] = np.nan
        out.append(d[:, ::-1].copy() if mirror else d)
    return out[0], out[1]


def _match_histogram(source: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``source`` (uint8) with its grey levels remapped so that its histogram matches
    ``reference``'s (histogram specification through the two cumulative distributions).

    SGBM's cost includes the raw intensities, so a global exposure or development difference
    between the views (common on antique cards, and Middlebury's ``E`` pairs) biases every match;
    one monotone look-up table removes it without touching the texture (measured: Adirondack with
    the other exposure's right view 18.9 -> 8.0 % bad-2, the same-exposure pair 8.8 -> 7.7 %)."""
    levels = np.arange(256, dtype=np.float64)
    src_hist = np.bincount(source.ravel(), minlength=256).astype(np.float64)
    ref_hist = np.bincount(reference.ravel(), minlength=256).astype(np.float64)
    # Each occupied level stands at the middle of its quantile band, and levels are interpolated
    # between them: a hard cumulative look-up moves a level to its neighbour whenever the two
    # views hold slightly different shares of it (measured: on a 10-level dark pair, 17 -> 28 %).
    src_mid = (np.cumsum(src_hist) - src_hist / 2) / src_hist.sum()
    ref_mid = (np.cumsum(ref_hist) - ref_hist / 2) / ref_hist.sum()
    src_used, ref_used = src_hist > 0, ref_hist > 0
    mapped = np.interp(src_mid, ref_mid[ref_used], levels[ref_used])
    lut = np.where(src_used, mapped, levels)
    lut = np.clip(np.rint(lut), 0, 255).astype(np.uint8)
    return cv2.LUT(source, lut)


def _lr_error(d_left: np.ndarray, d_right: np.ndarray) -> np.ndarray:
    """|d_left(x) - d_right(x - d_left(x))| (inf where either is missing)."""
    w = d_left.shape[1]
    xs = np.arange(w, dtype=np.float32)[None, :] - np.nan_to_num(d_left, nan=-1e4)
    xi = np.rint(xs).astype(np.int64)
    inside = (xi >= 0) & (xi < w) & np.isfinite(d_left)
    other = np.take_along_axis(d_right, np.clip(xi, 0, w - 1), axis=1)
    err = np.abs(d_left - other)
    err[~inside | ~np.isfinite(err)] = np.inf
    return err


def _fill_background(d: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Each invalid pixel takes the smaller of the nearest valid values left and right on its row
    (NaN where a row has none)."""
    h, w = d.shape
    # int32 column indices, the right-hand scan on a flipped copy and flat gathers: the same
    # values at half the time of int64 indices and take_along_axis (22 -> 11 ms on 800 x 750 px).
    cols = np.arange(w, dtype=np.int32)
    vals = np.where(valid, d, np.nan).ravel()
    row_start = np.arange(0, h * w, w, dtype=np.intp)[:, None]
    idx_l = np.maximum.accumulate(np.where(valid, cols, np.int32(-1)), axis=1)
    left = vals.take(row_start + np.maximum(idx_l, 0))
    left[idx_l < 0] = np.nan
    idx_r = np.minimum.accumulate(np.where(valid[:, ::-1], cols[::-1], np.int32(w)), axis=1)[:, ::-1]
    right = vals.take(row_start + np.minimum(idx_r, w - 1))
    right[idx_r >= w] = np.nan
    out = np.fmin(left, right)
    out[valid] = d[valid]
    return out


def _fill(d: np.ndarray, valid: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    filled = _fill_background(d, valid)
    missing = ~np.isfinite(filled)
    filled[missing] = fallback[missing]
    filled = np.nan_to_num(filled, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    smooth = cv2.medianBlur(filled, 5)
    return np.where(valid, filled, smooth).astype(np.float32)


# The weighted median's working resolution: 1/4 for maps whose shorter side is at least
# REFINE_QUARTER_MIN_SIDE px, else 1/2 (a quarter of a small map leaves too little to filter).
REFINE_QUARTER_MIN_SIDE = 400


def refine_reduction(shape: tuple[int, int]) -> tuple[int, int]:
    """(reduction, radius px at that reduction) of :func:`_refine`'s weighted median for a map of
    ``shape`` (H, W): about 16-18 px of the map either way."""
    return (4, 2) if min(shape) >= REFINE_QUARTER_MIN_SIDE else (2, 4)


def _refine(guide: np.ndarray, d: np.ndarray, trusted: np.ndarray) -> np.ndarray:
    """Edge-aware clean-up of the untrusted (filled / inconsistent) pixels: a weighted median guided
    by the image, at reduced resolution (:func:`refine_reduction`). Measured at half resolution:
    most of the full-resolution filter's gain, -0.5 points of mean bad-2, at a third of its 0.16 s.
    Its time is per pixel filtered (not per distinct disparity), so on maps of 400 px and more it
    runs at a quarter (radius 2): `keystone bench disparity --backend keystone`, 2026-11-25, mean
    bad-2 tuned 5.26 -> 5.38 % (Tsukuba, 288 px, stays at half), held out 4.32 -> 4.49 %, 0.23 ->
    0.17 s per 741 x 500 pair; on an 800 px rectified card view 0.06 -> 0.01 s per view."""
    h, w = d.shape
    if min(h, w) < 32 or not hasattr(cv2, "ximgproc"):
        return d
    reduction, radius = refine_reduction((h, w))
    small_size = (w // reduction, h // reduction)
    g = cv2.resize(guide, small_size, interpolation=cv2.INTER_AREA)
    small = cv2.resize(d, small_size, interpolation=cv2.INTER_NEAREST)
    med = cv2.ximgproc.weightedMedianFilter(g, small, radius, sigma=25.5)
    med = cv2.resize(med, (w, h), interpolation=cv2.INTER_NEAREST)
    return np.where(trusted, d, med).astype(np.float32)


def _sgbm_backend(L: np.ndarray, R: np.ndarray, params: DisparityParams, width: int) -> _BackendOutput:
    min_d, num = _search_range(params, None, width)
    d_left, d_right = _sgbm_pair(L, R, min_d, num, params.block_size)
    err = _lr_error(d_left, d_right)
    conf = _confidence(err, params.consistency_px)
    return d_left, d_right, conf, None


def _fit_vertical(flow: np.ndarray) -> tuple[float, float, float] | None:
    """Robust plane fit v = c0 + c1 x + c2 y to the flow's vertical component (subsampled).

    ``None`` when the flow does not support it (median residual > 1 px, or a correction larger than
    5 % of the height anywhere): then the pair is matched as given."""
    h, w = flow.shape[:2]
    step = max(1, int(np.sqrt(h * w / 20000)))
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    v = flow[::step, ::step, 1].ravel().astype(np.float64)
    A = np.stack([np.ones(v.size), xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    ok = np.isfinite(v)
    A, v = A[ok], v[ok]
    if v.size < 3:
        return None
    keep = np.ones(v.size, bool)
    c: np.ndarray = np.zeros(3)
    for _ in range(3):
        c, *_ = np.linalg.lstsq(A[keep], v[keep], rcond=None)
        res = np.abs(A @ c - v)
        keep = res <= max(np.percentile(res, 70), 1e-6)
    corners = np.array([[1, 0, 0], [1, w - 1, 0], [1, 0, h - 1], [1, w - 1, h - 1]], np.float64) @ c
    if np.median(res) > 1.0 or np.abs(corners).max() > 0.05 * h:
        return None
    return float(c[0]), float(c[1]), float(c[2])


def _keystone_backend(L: np.ndarray, R: np.ndarray, params: DisparityParams, width: int) -> _BackendOutput:
    h, w = L.shape
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)  # type: ignore[attr-defined]  # cv2's stubs lack the factory
    flow = np.asarray(dis.calc(L, R, None), np.float32)
    model = _fit_vertical(flow)
    shift = _dominant_shift(L, R) if params.disparity_range is None or model is None else None
    if model is None and shift is not None and abs(shift[1]) <= 0.05 * h:
        model = (shift[1], 0.0, 0.0)  # a plain vertical offset
    c0, c1, c2 = model if model is not None else (0.0, 0.0, 0.0)
    # A column and a row of coordinates: broadcasting gives the same float32 maps as full grids.
    ys, xs = np.arange(h, dtype=np.float32)[:, None], np.arange(w, dtype=np.float32)[None, :]
    cy = (h - 1) / 2.0
    map_x = xs - np.float32(c1) * (ys - np.float32(cy))
    map_y = ys + np.float32(c0) + np.float32(c1) * xs + np.float32(c2) * ys
    R2 = cv2.remap(R, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # rough disparity in the corrected grid (the horizontal correction moved the right view)
    rough = np.nan_to_num(-(flow[..., 0] + np.float32(c1) * (ys - np.float32(cy))), nan=0.0)
    dominant = shift[0] if shift is not None and params.disparity_range is None else None
    min_d, num = _search_range(params, rough, width, dominant)
    d_left, d_right = _sgbm_pair(L, _match_histogram(R2, L), min_d, num, params.block_size, pad=True)
    err_l = _lr_error(d_left, d_right)
    # Filling trusts every pixel SGBM kept (its uniqueness and speckle filters): measured here, an
    # extra left-right rejection before filling cost 1-5 points of bad-2 (it removes good pixels
    # near the mirrored pass's borders); the left-right check sets the confidence instead.
    ok_l = np.isfinite(d_left)
    ok_r = np.isfinite(d_right)
    conf = _confidence(err_l, params.consistency_px)
    rough_r = cv2.remap(rough, xs - rough, np.repeat(ys, w, axis=1), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    disp_left = _refine(L, _fill(d_left, ok_l, rough), err_l <= params.consistency_px)
    err_r = _lr_error(d_right[:, ::-1], d_left[:, ::-1])[:, ::-1]  # the same check from the right
    disp_right = _refine(R2, _fill(d_right, ok_r, rough_r), err_r <= params.consistency_px)
    return disp_left, disp_right, conf, model


# ------------------------------------------------------------------------------------ interface
def estimate_disparity(
    left: np.ndarray, right: np.ndarray, backend: str = DEFAULT_BACKEND, params: DisparityParams = DisparityParams()
) -> DisparityResult:
    """Disparity of both views of a rectified pair (conventions in the module docstring).

    Raises :class:`InvalidInputError` (NaN/inf input, mismatched sizes, bad shapes),
    :class:`ImageTooSmallError` (a side below ``MIN_SIDE``) and :class:`UnknownBackendError`.
    ``flags`` records what was noticed: ``textureless`` (nothing to match: disparity 0, confidence 0),
    ``contrast_stretched`` (dark / overexposed pair), ``low_confidence`` (< 20 % confident pixels).
    """
    if backend not in BACKENDS:
        raise UnknownBackendError(f"unknown disparity backend {backend!r}; choose from {', '.join(BACKENDS)}")
    start = time.perf_counter()
    L, R, flags = _prepare(left, right)
    h, w = L.shape
    vertical = None
    if "textureless" in flags:
        zero = np.zeros((h, w), np.float32)
        d_left, d_right, conf = zero, zero.copy(), zero.copy()
        if backend == "sgbm":
            d_left, d_right = np.full((h, w), np.nan, np.float32), np.full((h, w), np.nan, np.float32)
    elif backend == "sgbm":
        d_left, d_right, conf, vertical = _sgbm_backend(L, R, params, w)
    elif backend == "keystone":
        d_left, d_right, conf, vertical = _keystone_backend(L, R, params, w)
    else:
        d_left, d_right, conf, vertical = _flow_backend(backend, L, R, params)
    conf = np.clip(np.nan_to_num(conf, nan=0.0), 0.0, 1.0).astype(np.float32)
    fraction = float((conf >= 0.5).mean())
    if fraction < 0.2:
        flags = flags + ("low_confidence",)
    return DisparityResult(
        disp_left=np.asarray(d_left, np.float32),
        disp_right=np.asarray(d_right, np.float32),
        confidence=conf,
        confident_fraction=fraction,
        seconds=time.perf_counter() - start,
        backend=backend,
        flags=flags,
        vertical_model=vertical,
    )


# ----------------------------------------------------------------------------------------- depth
def depth_from_disparity(disp: np.ndarray, focal_px: float, baseline: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth up to scale, ``f * b / d``; zero, negative and non-finite disparities are masked
    (``valid`` False, depth 0 there): never an infinite depth."""
    if not (np.isfinite(focal_px) and focal_px > 0 and np.isfinite(baseline) and baseline > 0):
        raise InvalidInputError(f"focal_px ({focal_px}) and baseline ({baseline}) must be finite and > 0")
    d = np.asarray(disp, dtype=np.float64)
    valid = np.isfinite(d) & (d > 1e-6)
    depth = np.zeros(d.shape, np.float32)
    depth[valid] = (focal_px * baseline / d[valid]).astype(np.float32)
    valid &= np.isfinite(depth)
    depth[~valid] = 0.0
    return depth, valid


def normalised_inverse_depth(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(1/D - min) / (max - min)`` over valid pixels, in 0..1, 0 where invalid; a scene with a
    single depth (max == min) gives 1 on its valid pixels. Always finite."""
    out = np.zeros(np.shape(depth), np.float32)
    valid = np.asarray(valid, bool) & np.isfinite(depth) & (np.asarray(depth) > 0)
    if not valid.any():
        return out
    inv = 1.0 / np.asarray(depth, np.float64)[valid]
    lo, hi = inv.min(), inv.max()
    out[valid] = 1.0 if hi - lo <= 1e-12 * max(hi, 1e-300) else ((inv - lo) / (hi - lo)).astype(np.float32)
    return out


def resample_512(values: np.ndarray, valid: np.ndarray, size: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Resample a map to ``size x size`` (the release size) without mixing in invalid pixels:
    ``INTER_AREA`` on ``values * valid`` and on ``valid`` separately, then divide (a valid-weighted
    area average; ``INTER_LINEAR`` when upsampling). A 512 pixel is valid when at least half of what
    it covers was valid; invalid output pixels are 0."""
    v = np.asarray(valid, bool) & np.isfinite(values)
    src = np.where(v, values, 0).astype(np.float32)
    h, w = src.shape
    interp = cv2.INTER_AREA if (h >= size and w >= size) else cv2.INTER_LINEAR
    num = cv2.resize(src, (size, size), interpolation=interp)
    den = cv2.resize(v.astype(np.float32), (size, size), interpolation=interp)
    ok = den >= 0.5
    out = np.zeros((size, size), np.float32)
    out[ok] = num[ok] / den[ok]
    return out, ok
