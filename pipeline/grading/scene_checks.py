"""Measurements that look at what the depth map says about the scene, and at what the crop holds.

Each check is pure and cheap (a few ms on a 700 px view): it reads the rectified left view, its
left disparity map (``x_right = x_left - d``: larger ``d`` = nearer) and the photograph mask
(``True`` = not the warp's black fill), all ``(H, W)`` in the rectified view's own pixels.

* :func:`depth_order`: most photographs stand on the ground: lower rows are nearer than upper
  rows and the top (sky, ceilings, far walls) is far. A depth map upside down or reversed
  (swapped eyes) reads the other way.
* :func:`streak_fraction`: row streaks, the signature of a matcher that lost the rows (scan-line
  optimisation, misaligned rows, sky and water): horizontal runs of near-constant disparity that
  break against the rows above and below.
* :func:`sky_near_fraction`: textureless areas in the upper half (sky, blank print) that read
  nearer than the textured scene; a matcher has nothing to match there, and sky is far.
* :func:`reflection_symmetry`: the lower part mirroring the upper about a horizon row, in
  intensity and in disparity: water reflections read as a second, mirrored scene.
* :func:`border_intrusion`: straight edges along the crop border (card edge, mount) and
  high-contrast strokes inside the border strip (mount text, captions).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "BorderIntrusion",
    "Reflection",
    "border_intrusion",
    "depth_order",
    "reflection_symmetry",
    "sky_near_fraction",
    "streak_fraction",
]

CHECK_SIDE = 256  # px: depth ordering, sky, reflections and the border are judged at this longer side
STREAK_SIDE = 512  # px: streaks are a few rows thick; judged at this longer side (rows kept by striding)
STREAK_RUN = 0.06  # a streak runs at least this share of the view width (and >= 8 px)
FLAT_STD = 2.5  # grey levels: a 9x9 window steadier than this (at CHECK_SIDE) is textureless
BORDER_STRIP = 0.10  # share of the view's side examined along each border
EDGE_STEP = 25.0  # grey levels over 2 px at CHECK_SIDE: a card edge or ink stroke at least this steep
STROKE_CONTRAST = 40.0  # grey levels: a stroke darker than its 9x9 surroundings' maximum by at least this


def _shrink(image: np.ndarray, side: int, interpolation: int = cv2.INTER_AREA) -> tuple[np.ndarray, float]:
    """``image`` with its longer side at most ``side`` px, and the scale applied (<= 1)."""
    h, w = image.shape[:2]
    scale = min(1.0, side / max(h, w))
    if scale >= 1.0:
        return image, 1.0
    size = (max(8, round(w * scale)), max(8, round(h * scale)))
    return cv2.resize(image, size, interpolation=interpolation), size[0] / w


def _small_disparity(disp: np.ndarray, inside: np.ndarray, side: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Disparity by striding (no averaging across depth edges or streaks) and its valid mask; the
    values stay in full-resolution px."""
    h, w = disp.shape
    step = max(1, int(np.ceil(max(h, w) / side)))
    small = disp[::step, ::step]
    valid = inside[::step, ::step] & np.isfinite(small)
    return np.where(valid, small, np.nan).astype(np.float32), valid, 1.0 / step


def depth_order(disp: np.ndarray, inside: np.ndarray) -> float | None:
    """Signed plausibility of the depth ordering in [-1, 1] (dimensionless).

    ``(median d over the lowest third of the photograph's rows - median d over the highest third)
    / (p95 - p5 of d)``: +1 = the bottom is as much nearer than the top as the whole depth range,
    0 = no vertical ordering, negative = the top reads nearer than the bottom (upside down,
    reversed by swapped eyes, or a near blob in the sky). ``None`` when fewer than 100 pixels
    have a disparity or the range is under 1 px (nothing to order)."""
    small, valid, _ = _small_disparity(disp, inside, CHECK_SIDE)
    if valid.sum() < 100:
        return None
    rows = np.flatnonzero(valid.any(axis=1))
    top, bottom = rows[0], rows[-1] + 1
    third = max(1, (bottom - top) // 3)
    upper = small[top : top + third][valid[top : top + third]]
    lower = small[bottom - third : bottom][valid[bottom - third : bottom]]
    values = small[valid]
    p5, p95 = np.percentile(values, [5, 95])
    if upper.size < 10 or lower.size < 10 or p95 - p5 < 1.0:
        return None
    return float(np.clip((np.median(lower) - np.median(upper)) / (p95 - p5), -1.0, 1.0))


def streak_fraction(disp: np.ndarray, inside: np.ndarray) -> float | None:
    """Share (0..1) of the photograph covered by row streaks in the disparity.

    A pixel is on a streak when its disparity is flat along the row (``|d(x+1) - d(x)|`` under a
    quarter of the step) while it stands out from the rows 2 above *and* 2 below by at least the
    step, on the same side (a ridge or a trough across rows, not a depth edge, which changes
    on one side only); the step is ``max(1 px, 3 % of p95 - p5)``. Streak pixels count only in
    horizontal runs of at least 6 % of the width (and 8 px). ``None`` with fewer than 100
    disparities. Judged at 512 px by striding, so a streak keeps its rows."""
    small, valid, _ = _small_disparity(disp, inside, STREAK_SIDE)
    h, w = small.shape
    if valid.sum() < 100 or h < 8 or w < 8:
        return None
    p5, p95 = np.percentile(small[valid], [5, 95])
    step = max(1.0, 0.03 * float(p95 - p5))
    d = np.where(valid, small, 0.0).astype(np.float32)
    up = np.zeros_like(d)
    down = np.zeros_like(d)
    up[2:] = d[2:] - d[:-2]
    down[:-2] = d[:-2] - d[2:]
    both = valid.copy()
    both[2:] &= valid[:-2]
    both[:-2] &= valid[2:]
    both[:2] = both[-2:] = False
    ridge = both & (np.abs(up) >= step) & (np.abs(down) >= step) & (np.sign(up) == np.sign(down))
    flat = np.zeros_like(valid)
    flat[:, :-1] = valid[:, :-1] & valid[:, 1:] & (np.abs(d[:, 1:] - d[:, :-1]) < 0.25 * step)
    candidate = (ridge & flat).astype(np.uint8)
    run = max(8, round(STREAK_RUN * w))
    if run > w:
        return 0.0
    # A run of `run` candidates in a row: the box mean over the run is 1 at its centre; dilating
    # those centres by the run gives back every pixel of every long enough run.
    kernel_x = np.ones((1, run), np.float32) / run
    full = cv2.filter2D(candidate.astype(np.float32), -1, kernel_x, borderType=cv2.BORDER_CONSTANT) > 0.999
    streaks = cv2.dilate(full.astype(np.uint8), np.ones((1, run), np.uint8)) & candidate
    # The ridge test marks a streak's edges rows; grow by 1 row so a 3-row streak counts whole.
    streaks = cv2.dilate(streaks, np.ones((3, 1), np.uint8)) & valid.astype(np.uint8)
    return float(streaks.sum() / max(1, valid.sum()))


def _local_std(grey: np.ndarray, size: int = 9) -> np.ndarray:
    g = grey.astype(np.float32)
    mean = cv2.blur(g, (size, size))
    mean_sq = cv2.blur(g * g, (size, size))
    return np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))


def sky_near_fraction(grey: np.ndarray, disp: np.ndarray, inside: np.ndarray) -> float | None:
    """Share (0..1) of the upper half of the photograph that is textureless (9x9 grey standard
    deviation under 2.5 grey levels at 256 px: sky, blank print, fog) and yet reads nearer than
    the median of the textured pixels. ``None`` when fewer than 100 pixels are textured and
    have a disparity (nothing to compare with)."""
    small_grey, _ = _shrink(grey, CHECK_SIDE)
    sh, sw = small_grey.shape
    small_disp = cv2.resize(
        np.where(np.isfinite(disp), disp, np.nan).astype(np.float32), (sw, sh), interpolation=cv2.INTER_NEAREST
    )
    inside_u8 = cv2.resize(inside.astype(np.uint8), (sw, sh), interpolation=cv2.INTER_NEAREST)
    small_inside = np.asarray(cv2.erode(inside_u8, np.ones((5, 5), np.uint8)) > 0)
    has = small_inside & np.isfinite(small_disp)
    flat = _local_std(small_grey) < FLAT_STD
    textured = has & ~flat
    if textured.sum() < 100:
        return None
    reference = float(np.median(small_disp[textured]))
    rows = np.flatnonzero(small_inside.any(axis=1))
    if rows.size == 0:
        return None
    upper = np.zeros_like(small_inside)
    upper[rows[0] : rows[0] + max(1, (rows[-1] + 1 - rows[0]) // 2)] = True
    region = upper & small_inside
    if not region.any():
        return None
    near_flat = region & flat & has & (np.nan_to_num(small_disp, nan=-np.inf) > reference)
    return float(near_flat.sum() / region.sum())


@dataclass(frozen=True)
class Reflection:
    """``symmetry`` in [0, 1]: the smaller of the intensity and disparity correlations between
    the band above ``row_px`` and the mirrored band below it (0 = none or anti-correlated);
    ``row_px``: the horizon row in the rectified view's pixels."""

    symmetry: float
    row_px: int


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    denominator = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denominator) if denominator > 1e-9 else 0.0


def reflection_symmetry(grey: np.ndarray, disp: np.ndarray, inside: np.ndarray) -> Reflection | None:
    """The strongest mirror symmetry of the lower part about a horizon row (see :class:`Reflection`).

    Horizons from 30 % to 75 % of the height are tried, each band at least 12 % of the height
    (at 128 px, grey smoothed); a band must be at least 80 % photograph. ``None`` when the view
    is under 32 px high or no disparity is there."""
    small_grey, scale = _shrink(grey, CHECK_SIDE // 2)
    sh, sw = small_grey.shape
    if sh < 32:
        return None
    g = cv2.GaussianBlur(small_grey.astype(np.float32), (0, 0), 1.0)
    d = cv2.resize(np.where(np.isfinite(disp), disp, np.nan).astype(np.float32), (sw, sh), interpolation=cv2.INTER_NEAREST)
    ok = cv2.resize(inside.astype(np.uint8), (sw, sh), interpolation=cv2.INTER_NEAREST).astype(bool) & np.isfinite(d)
    if ok.sum() < 100:
        return None
    d = np.where(ok, d, 0.0)
    best = Reflection(0.0, 0)
    band_min = max(4, round(0.12 * sh))
    for row in range(round(0.30 * sh), round(0.75 * sh) + 1):
        band = min(row, sh - row, round(0.25 * sh))
        if band < band_min:
            continue
        above = slice(row - band, row)
        below = slice(row + band - 1, row - 1, -1) if row - 1 >= 0 else slice(row + band - 1, None, -1)
        keep = ok[above] & ok[below]
        if keep.mean() < 0.8:
            continue
        intensity = _ncc(g[above][keep], g[below][keep])
        depth = _ncc(d[above][keep], d[below][keep])
        symmetry = max(0.0, min(intensity, depth))
        if symmetry > best.symmetry:
            best = Reflection(round(symmetry, 6), round(row / scale))
    return best


@dataclass(frozen=True)
class BorderIntrusion:
    """``line``: the largest share (0..1) of a line parallel to a border, inside the border strip,
    crossed by a steep same-signed edge (a card edge or mount line: 1 = the whole border);
    ``strokes``: share (0..1) of the most inked border strip that is ink-like strokes (darker than their
    surroundings by 40 grey levels) beyond the share in the rest of the photograph;
    ``side``: the border where ``line`` is largest (top, bottom, left, right)."""

    line: float
    strokes: float
    side: str


def border_intrusion(grey: np.ndarray, inside: np.ndarray) -> BorderIntrusion | None:
    """Card edge or mount text inside the crop (see :class:`BorderIntrusion`), judged at 256 px in
    a strip 10 % of the side wide along each border of the photograph's bounding box, 3 px in
    from the warp's fill (its own edge is not the card's). ``None`` for views under 32 px."""
    small, _ = _shrink(grey, CHECK_SIDE)
    sh, sw = small.shape
    if min(sh, sw) < 32:
        return None
    inside_u8 = cv2.resize(inside.astype(np.uint8), (sw, sh), interpolation=cv2.INTER_NEAREST)
    mask = np.asarray(cv2.erode(inside_u8, np.ones((7, 7), np.uint8)) > 0)
    if mask.sum() < 100:
        return None
    g = small.astype(np.float32)
    # Edge across rows (for top/bottom borders) and across columns (left/right), over 2 px,
    # tolerant of a slight slant by taking the strongest of 3 neighbouring lines.
    gy = np.zeros_like(g)
    gy[1:-1] = g[2:] - g[:-2]
    gx = np.zeros_like(g)
    gx[:, 1:-1] = g[:, 2:] - g[:, :-2]
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    sy = max(2, round(BORDER_STRIP * (y1 - y0)))
    sx = max(2, round(BORDER_STRIP * (x1 - x0)))

    flat = _local_std(g, 5) < 2 * FLAT_STD

    def coverage(rs: slice, cs: slice, gradient: np.ndarray, axis: int, outward: bool) -> float:
        """Largest share of a line parallel to the border crossed by a steep edge of one sign,
        counting only lines whose outer side (between them and the border, at least 2 px) is
        mostly flat: a card or mount strip, not a horizon or a shelf in the picture."""
        grad, valid, smooth = gradient[rs, cs], mask[rs, cs], flat[rs, cs]
        if axis == 0:  # lines are columns: work on the transpose, lines as rows
            grad, valid, smooth = grad.T, valid.T, smooth.T
        if outward:  # index 0 at the border
            grad, valid, smooth = grad[::-1], valid[::-1], smooth[::-1]
        totals = valid.sum(axis=1)
        flat_share = np.cumsum((smooth & valid).sum(axis=1)) / np.maximum(np.cumsum(totals), 1)
        outer_flat = np.zeros(len(totals), bool)
        outer_flat[2:] = flat_share[1:-1] >= 0.6  # the rows before this one
        enough = (totals >= 0.5 * valid.shape[1]) & outer_flat
        best = 0.0
        for sign in (1.0, -1.0):
            steep = ((sign * grad) >= EDGE_STEP) & valid
            steep = cv2.dilate(steep.astype(np.uint8), np.ones((3, 1), np.uint8)).astype(bool) & valid
            if enough.any():
                best = max(best, float((steep.sum(axis=1)[enough] / totals[enough]).max()))
        return best

    strips = {
        "top": (slice(y0, y0 + sy), slice(None), gy, 1, False),
        "bottom": (slice(y1 - sy, y1), slice(None), gy, 1, True),
        "left": (slice(None), slice(x0, x0 + sx), gx, 0, False),
        "right": (slice(None), slice(x1 - sx, x1), gx, 0, True),
    }
    lines = {side: coverage(*spec) for side, spec in strips.items()}
    side = max(lines, key=lambda name: lines[name])

    # Ink strokes: pixels much darker than the brightest pixel around them (thin dark lines on
    # light card), in the border strip versus the interior.
    # Ink on card: the 9x9 surroundings are mostly one bright level (their median near their
    # maximum), and the pixel is far below it. Dark detail in a photograph has no such plain ground.
    background = cv2.medianBlur(np.clip(g, 0, 255).astype(np.uint8), 9).astype(np.float32)
    brightest = cv2.dilate(g, np.ones((9, 9), np.uint8))
    stroke = ((background - g) >= STROKE_CONTRAST) & ((brightest - background) <= 15.0)
    border = np.zeros_like(mask)
    shares = []
    for rs, cs, *_ in strips.values():
        border[rs, cs] = True
        inside_strip = mask[rs, cs]
        if inside_strip.any():
            shares.append(float(stroke[rs, cs][inside_strip].mean()))
    interior = mask & ~border
    if not shares or not interior.any():
        return BorderIntrusion(round(lines[side], 6), 0.0, side)
    strokes = max(0.0, max(shares) - float(stroke[interior].mean()))
    return BorderIntrusion(round(lines[side], 6), round(strokes, 6), side)
