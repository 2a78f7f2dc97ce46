"""Find the gutter between the two photos of a stereo card and box each photo.

Cards come in three kinds, and one method has to serve all of them:

- *mounted cards* (NYPL full cards): two photos on a card mount with borders, captions, side
  titles, sometimes arched tops; a strip of plain mount separates the photos;
- *raw scans* (Keystone-Mast): greyscale side-by-side frames from a negative, no mount, film
  edges; the frames meet at a thin dark line or a black strip;
- *cropped pairs* (``.jps``): two photos directly abutting; the join may be nearly invisible.

The card is never just cut at the middle (outer borders are rarely symmetric). Method, on a
grey copy downscaled to ``analysis_width`` (and a band-passed copy at ``similarity_width``):

1. **Period.** The right photo repeats the left one shifted by the period ``P`` (about a photo
   width plus the gutter) and a small vertical offset ``dy``. Both come from the normalised
   cross-correlation (NCC) of a template cut from inside the left half against the right half
   (``cv2.matchTemplate``); the peak NCC says how stereo-like the card is.
2. **Similarity.** Each column strip of the left photo has a partner ``P`` to its right, each
   strip of the right photo one ``P`` to its left. Per column ``t``, ``fwd(t)`` is the best NCC
   of the strip at ``t`` with the strip at ``t + P + d``, and ``bwd(t)`` the same towards
   ``t - P - d``, for ``|d|`` up to ``disparity_tolerance`` (disparity varies with depth);
   plain strips score 0. The similarity score of a split at ``x`` is
   ``sum(fwd[:x]) - sum(bwd[:x])``: columns left of it find their partner forward, columns right
   of it backward. This alone places the join of abutting photos, where no gutter is visible.
3. **Gutter.** Column profiles give direct evidence, each relative to the neighbouring columns:
   a *strip* is a dip in the columns' grey-level spread (plain mount, film edge, grey bar); a
   *seam* is a peak in the mean horizontal gradient (a thin line, or unrelated content meeting).
4. **Choice.** Inside ``search_band``, splits whose similarity score is within ``plateau`` of
   the best are eligible (the score is flat across a plain gutter); among them the split with
   the most gutter evidence wins, and one landing in a plain strip moves to the strip's centre.
   Without stereo similarity (a card back, a blank card) gutter evidence alone decides, and
   without either the split falls back to the middle (``method="centre"``, confidence 0).
5. **Boxes.** Each half loses its borders: a border ends at a *straight edge* (most pixels of a
   row or column change across it) with only *foreign* lines outside it. A column (over the
   middle rows) is foreign if it is plain or has no partner in the other half (mount, side
   titles, film edge, scan background). A row is foreign only if it is plain *and* partnerless,
   since rows inside a photo can be plain (sky, water, a road); top and bottom edges must also
   be straighter (``row_edge_fraction``). So a plain sky that reaches the top of a raw scan
   keeps its place in the box (it meets the trees along a ragged line), and so does a road whose
   markings have partners in the other half. Boxes are conservative: a mount with printed
   titles may stay partly inside. The boxes then get ``margin`` and the same size (the larger
   of the two, limited to what fits in each half), each centred on its photo.

Conventions: arrays are ``uint8`` ``(H, W)`` grey or ``(H, W, 3)`` RGB; boxes are
``(x0, y0, x1, y1)`` in card pixels with ``x1``/``y1`` exclusive; the left box lies in
``[0, gutter_x)`` and the right box in ``[gutter_x, W)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import median_filter

from .contracts import check_image
from .errors import InvalidInputError

Box = tuple[int, int, int, int]

MIN_WIDTH = 32  # px: below this there is no pair of photos to speak of
MIN_HEIGHT = 16

_MATCHED = 0.4  # strip NCC above which a line has a partner in the other half
_PLAIN = 0.15  # textured fraction below which a line is plain


@dataclass(frozen=True)
class SplitParams:
    """Parameters of :func:`split_card`. Fractions are of the card's width unless stated."""

    search_band: tuple[float, float] = (0.35, 0.65)
    """The split column is searched in this band, as fractions of the card width."""
    analysis_width: int = 800
    """px: the card is downscaled (area filter) to at most this width for all analysis."""
    similarity_width: int = 320
    """px: width of the band-passed copy used for the period and the half-to-half similarity."""
    disparity_tolerance: float = 0.03
    """Horizontal slack (fraction of width) when a strip is compared with its partner."""
    plateau: float = 0.15
    """Splits whose similarity score is within this fraction of the score's range in the band
    below the best are eligible."""
    texture_threshold: float = 6.0
    """Grey levels per pixel: a smoothed gradient above this marks a pixel as textured."""
    edge_threshold: float = 4.0
    """Grey levels: a pixel changes across a straight edge if it differs by more than this."""
    edge_fraction: float = 0.6
    """Fraction of a column's pixels (middle rows) that must change across a photo's side edge."""
    row_edge_fraction: float = 0.9
    """The same for a row across a photo's top or bottom edge. Stricter, because rows inside a
    photo often run from plain sky or ground into content along a ragged line that changes
    most, but not nearly all, pixels (measured: false edges 0.60-0.82, true ones 0.99-1.00)."""
    max_border: float = 0.25
    """A border is looked for only in the outer quarter of each half, on each side (fraction of
    the half's width or height)."""
    margin: float = 0.01
    """Added around each detected photo, as a fraction of the card width."""

    def __post_init__(self) -> None:
        # Wiring errors surface when parameters are built, not halfway through a run.
        low, high = self.search_band
        if not 0.0 < low < high < 1.0:
            raise InvalidInputError(f"Expected 0 < search_band[0] < search_band[1] < 1, got {self.search_band}")
        if self.analysis_width < MIN_WIDTH or self.similarity_width < MIN_WIDTH:
            raise InvalidInputError(
                f"Expected analysis_width and similarity_width >= {MIN_WIDTH} px, "
                f"got {self.analysis_width} and {self.similarity_width}"
            )
        for name in ("disparity_tolerance", "plateau", "edge_fraction", "row_edge_fraction", "max_border", "margin"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InvalidInputError(f"Expected 0 <= {name} <= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class CardSplit:
    """Where a card was split and where its two photos are."""

    left_box: Box  # (x0, y0, x1, y1) in original card pixels, x1/y1 exclusive
    right_box: Box
    gutter_x: int  # split column in card pixels: the left box ends at or before it, the right begins at or after
    method: str  # "gutter" (strip or seam seen), "similarity" (halves' content), "centre" (no evidence)
    confidence: float  # 0..1: how stereo-like the halves are, and how clear the gutter is


def check_card(card: np.ndarray) -> None:
    """Raise :class:`InvalidInputError` unless ``card`` is a uint8 ``(H, W)`` or ``(H, W, 3)``
    array of at least ``MIN_WIDTH`` x ``MIN_HEIGHT`` pixels."""
    check_image(card, "a card", MIN_WIDTH, MIN_HEIGHT)


# ---------------------------------------------------------------------------------- helpers


def _grey(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _resize_to_width(image: np.ndarray, width: int) -> np.ndarray:
    height, current = image.shape[:2]
    if current <= width:
        return image
    return cv2.resize(image, (width, max(1, round(height * width / current))), interpolation=cv2.INTER_AREA)


def _box_sum(values: np.ndarray, k: int) -> np.ndarray:
    """Sum over a centred window of ``k`` samples (zero padded); same length as ``values``,
    also when it is shorter than the window (``np.convolve(mode="same")`` is not)."""
    if k <= 1:
        return values
    half = k // 2
    cumulative = np.cumsum(np.concatenate((np.zeros(half + 1), values, np.zeros(k - half - 1))))
    return cumulative[k:] - cumulative[:-k]


def _local_median(values: np.ndarray, half_window: int) -> np.ndarray:
    """Running median over ``2 * half_window + 1`` samples (edges padded by repetition)."""
    return median_filter(values, size=2 * half_window + 1, mode="nearest")


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` of each run of True in a 1-D boolean array."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return [(int(s), int(e)) for s, e in zip(edges[::2], edges[1::2])]


def _resample(values: np.ndarray, size: int) -> np.ndarray:
    """Sample-centre linear resampling of a 1-D profile to ``size`` samples."""
    positions = (np.arange(size) + 0.5) * (values.size / size) - 0.5
    return np.interp(positions, np.arange(values.size), values)


def _overlap_rows(height: int, dy: int) -> tuple[slice, slice]:
    """Rows of a left-half member and of its partner ``dy`` rows lower, where both exist."""
    return (slice(0, height - dy), slice(dy, height)) if dy >= 0 else (slice(-dy, height), slice(0, height + dy))


# ------------------------------------------------------------------------- stereo similarity


def _period(band: np.ndarray) -> tuple[int, int, float]:
    """``(P, dy, ncc)``: shift of the right half against the left half of a band-passed image.

    A template from inside the left half (columns 10-38 %, rows inside a 6 % margin) is searched
    at horizontal shifts of 35-62 % of the width and vertical shifts up to 6 % of the height.
    """
    height, width = band.shape
    t0 = int(0.10 * width)
    t1 = max(t0 + 2, int(0.38 * width))
    dy_max = max(1, round(0.06 * height))
    s_min, s_max = max(1, int(0.35 * width)), min(int(0.62 * width), width - t1)
    template = band[dy_max : height - dy_max, t0:t1]
    if template.shape[0] < 4 or s_max < s_min or float(template.std()) < 1e-3:
        return round(width / 2), 0, 0.0
    ncc = cv2.matchTemplate(band[:, t0 + s_min : t1 + s_max], template, cv2.TM_CCOEFF_NORMED)
    ncc = np.nan_to_num(ncc, nan=0.0, posinf=0.0, neginf=0.0)  # (2 dy_max + 1, s_max - s_min + 1)
    row, col = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
    return s_min + int(col), int(row) - dy_max, float(ncc[row, col])


def _fwd_bwd(band: np.ndarray, period: int, dy: int, tolerance: int, strip: int) -> tuple[np.ndarray, np.ndarray]:
    """Per column: best NCC of the ``strip`` columns around it with their partner ``period`` to
    the right (fwd) and to the left (bwd)."""
    height, width = band.shape
    rows_a, rows_b = _overlap_rows(height, dy)
    a, b = band[rows_a], band[rows_b]
    energy_a = _box_sum((a * a).sum(axis=0, dtype=np.float64), strip)
    energy_b = _box_sum((b * b).sum(axis=0, dtype=np.float64), strip)
    # Strips with almost no band-pass energy (plain mount, film edge, blank) have no reliable
    # partner: they score 0 rather than a noisy NCC.
    floor = 0.05 * float(np.median(energy_a)) + 1e-6
    fwd, bwd = np.zeros(width), np.zeros(width)
    for shift in range(max(1, period - tolerance), min(width - 1, period + tolerance) + 1):
        n = width - shift
        product = _box_sum((a[:, :n] * b[:, shift:]).sum(axis=0, dtype=np.float64), strip)
        ea, eb = energy_a[:n], energy_b[shift:]
        ncc = product / np.sqrt(ea * eb + 1e-12)
        ncc[(ea < floor) | (eb < floor)] = 0.0
        fwd[:n] = np.maximum(fwd[:n], ncc)
        bwd[shift:] = np.maximum(bwd[shift:], ncc)
    return fwd, bwd


def _row_similarity(band: np.ndarray, x0: int, x1: int, period: int, dy: int, tolerance: int) -> np.ndarray:
    """Per row of the left half: best NCC of the row strip over columns [x0, x1) with its
    partner ``period`` to the right and ``dy`` lower (0 for plain or partnerless rows)."""
    height, width = band.shape
    rows_a, rows_b = _overlap_rows(height, dy)
    shifts = np.arange(max(1, period - tolerance), min(width - 1, period + tolerance) + 1)
    x1 = min(x1, width - int(shifts[-1])) if shifts.size else x0
    out = np.zeros(height)
    if x1 - x0 < 2:
        return out
    a = band[rows_a, x0:x1]  # (r, n)
    b = band[rows_b][:, x0 + shifts[:, None] + np.arange(x1 - x0)]  # (r, shifts, n): every partner strip
    box = np.ones((3, 1))  # sum over 3 rows
    product = cv2.filter2D(np.einsum("rn,rsn->rs", a, b), -1, box, borderType=cv2.BORDER_CONSTANT)
    energy_a = _box_sum((a * a).sum(axis=1, dtype=np.float64), 3)[:, None]
    energy_b = cv2.filter2D(np.einsum("rsn,rsn->rs", b, b), -1, box, borderType=cv2.BORDER_CONSTANT)
    ncc = product / np.sqrt(energy_a * energy_b + 1e-12)
    floor = 0.05 * float(np.median(energy_a)) + 1e-6
    ncc[(energy_a < floor) | (energy_b < floor)] = 0.0  # plain rows have no partner
    out[rows_a] = np.maximum(ncc.max(axis=1), 0.0)
    return out


# ---------------------------------------------------------------------------------- analysis


@dataclass
class _Analysis:
    """Everything :func:`split_card` measures, at analysis scale unless stated."""

    scale: float  # card px per analysis px
    smooth: np.ndarray  # (h, w) float32 grey, lightly smoothed
    textured: np.ndarray  # (h, w) bool: pixel has texture
    band: np.ndarray  # (hc, wc) float32 band-passed coarse copy
    period: int  # coarse px
    dy: int  # coarse px
    period_ncc: float
    tolerance: int  # coarse px
    fwd: np.ndarray  # (w,) narrow-strip NCC with the partner to the right
    bwd: np.ndarray  # (w,) narrow-strip NCC with the partner to the left
    similarity: np.ndarray  # (w + 1,): similarity score of a split before column x
    strip: np.ndarray  # (w,) 0..1: column is part of a plain strip
    seam: np.ndarray  # (w,) 0..1: column is a seam line or a content jump


def _analyse(card: np.ndarray, params: SplitParams) -> _Analysis:
    grey = _resize_to_width(_grey(card), params.analysis_width)
    a_height, a_width = grey.shape
    smooth = cv2.GaussianBlur(grey, (0, 0), 1.0).astype(np.float32)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3) / 8.0  # grey levels per pixel
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    textured = (np.abs(gx) + np.abs(gy)) > params.texture_threshold

    coarse = _resize_to_width(smooth, params.similarity_width)
    c_width = coarse.shape[1]
    # Band-pass: keeps structure of a few coarse px and drops plain areas (~0). The low part is
    # removed along rows only, which also removes lines that run across the whole card (card
    # and mount edges, scan background): they are the same at every shift and would make any
    # two columns look alike.
    fine = cv2.GaussianBlur(coarse, (0, 0), 1.5)
    band = fine - cv2.GaussianBlur(fine, (61, 1), 10.0, sigmaY=0.1)
    period, dy, period_ncc = _period(band)
    tolerance = max(1, round(params.disparity_tolerance * c_width))
    # Wide strips (~3 % of the width) for a stable split score; narrow ones for sharp borders.
    fwd, bwd = _fwd_bwd(band, period, dy, tolerance, max(3, c_width // 36) | 1)
    # The sharp ones also use a narrower band: the wide one smears a photo's edge rows some
    # 25 analysis px into the mount beside it, which would then seem to have a partner.
    narrow = fine - cv2.GaussianBlur(fine, (15, 1), 2.5, sigmaY=0.1)
    fwd_sharp, bwd_sharp = _fwd_bwd(narrow, period, dy, tolerance, 3)
    cumulative = np.concatenate(([0.0], np.cumsum(fwd - bwd)))  # [i]: split before coarse column i
    similarity = np.interp(np.arange(a_width + 1) * (c_width / a_width), np.arange(c_width + 1), cumulative)

    half_window = max(3, a_width // 50)  # neighbourhood of +-2 % of the width
    rows = slice(a_height // 20, max(a_height // 20 + 1, a_height - a_height // 20))
    spread = smooth[rows].std(axis=0)
    around = _local_median(spread, half_window)
    # A dip counts only beside columns with content (a spread of 8+ grey levels): on a blank
    # card every column is plain, and none of them is a gutter.
    strip = np.clip((1.0 - spread / (around + 1.0) - 0.25) / 0.5, 0.0, 1.0) * np.clip((around - 2.0) / 6.0, 0.0, 1.0)
    jump = np.abs(gx).mean(axis=0)
    seam = np.clip((jump / (_local_median(jump, half_window) + 0.5) - 1.5) / 2.0, 0.0, 1.0)
    seam = np.maximum(seam, np.maximum(np.roll(seam, 1), np.roll(seam, -1)))  # a thin line has two edges
    return _Analysis(
        scale=card.shape[1] / a_width,
        smooth=smooth,
        textured=textured,
        band=band,
        period=period,
        dy=dy,
        period_ncc=period_ncc,
        tolerance=tolerance,
        fwd=_resample(fwd_sharp, a_width),
        bwd=_resample(bwd_sharp, a_width),
        similarity=similarity,
        strip=strip,
        seam=seam,
    )


def _search_range(params: SplitParams, a_width: int) -> tuple[int, int]:
    """``[lo, hi]``: split positions (analysis px) allowed by ``search_band``."""
    lo = max(1, int(params.search_band[0] * a_width))
    hi = min(a_width - 1, int(np.ceil(params.search_band[1] * a_width)))
    if hi < lo:
        lo = hi = a_width // 2
    return lo, hi


def _choose_split(an: _Analysis, params: SplitParams) -> tuple[int, str, float]:
    """``(x, method, confidence)``: the split (analysis px; columns < x are left)."""
    a_width = an.strip.size
    lo, hi = _search_range(params, a_width)
    xs = np.arange(lo, hi + 1)
    evidence = np.maximum(an.strip, an.seam)[np.minimum(xs, a_width - 1)]  # a split at x cuts before column x
    score_sim = an.similarity[xs]
    spread = float(score_sim.max() - score_sim.min())
    # Stereo strength: 0 up to period NCC 0.35 (card backs measure 0.16-0.26), 1 from 0.65 (real
    # pairs measure 0.68-0.98).
    strength = float(np.clip((an.period_ncc - 0.35) / 0.3, 0.0, 1.0))
    sim_norm = (score_sim - score_sim.min()) / spread if spread > 1e-9 else np.zeros(xs.size)
    if strength > 0.0:
        eligible = sim_norm >= 1.0 - params.plateau
    else:
        # No stereo evidence (a card back, a blank or textureless card): only a gutter close to
        # the middle is believed.
        eligible = np.abs(xs - a_width / 2) <= 0.05 * a_width
    centre_pull = 1.0 - np.abs(xs - a_width / 2) / a_width  # breaks exact ties only
    score = np.where(eligible, evidence + strength * sim_norm + 0.02 * centre_pull, -np.inf)
    i = int(np.argmax(score))
    best, gutter = int(xs[i]), float(evidence[i])
    # A gutter is usually a plain strip between two seams (the photos' edges), and the seams
    # score highest: move the split to the centre of a strip that touches or lies within 1 %
    # of the width of the chosen column.
    reach = max(2, a_width // 100)
    strips = [(start, end) for start, end in _runs(an.strip >= 0.3) if end - start >= 2]
    near = [(start, end) for start, end in strips if start - reach <= best <= end + reach]
    if near:
        start, end = min(near, key=lambda run: abs((run[0] + run[1]) / 2 - best))
        best = int(np.clip((start + end) // 2, lo, hi))
        gutter = max(gutter, float(an.strip[start:end].max()))
    confidence = round(float(np.clip(0.6 * strength + 0.4 * gutter, 0.0, 1.0)), 4)
    if gutter >= 0.5:
        return best, "gutter", confidence
    if strength > 0.0:
        return best, "similarity", confidence
    return a_width // 2, "centre", 0.0


# -------------------------------------------------------------------------------- photo boxes


def _border(
    lines: np.ndarray,
    textured: np.ndarray,
    matched: np.ndarray,
    columns: bool,
    params: SplitParams,
    max_width: int | None = None,
) -> int:
    """Width of the border at the start of ``lines`` (0 if none): one side of one half.

    ``lines``: ``(n, m)`` grey levels, line 0 outermost (rows, or transposed columns);
    ``textured``: ``(n, m)`` texture mask; ``matched``: ``(n,)`` partner NCC of each line;
    ``columns``: the lines are columns; ``max_width``: an upper bound on the border (lines).
    A border ends where at least ``edge_fraction`` of a
    column's (``row_edge_fraction`` of a row's) pixels change by more than ``edge_threshold``
    (comparing ``k`` lines either side, which tolerates a slightly tilted scan) and the lines
    outside are foreign to the photo: the ``k`` lines beyond a gap of ``g`` (where a photo's
    partner NCC still smears) plain and foreign, and half of the lines from there outwards
    foreign. Of the
    qualifying edges the innermost wins: a card's edge against the scan background lies
    outside the photo's edge.
    """
    n = lines.shape[0]
    k = max(2, n // 150)
    # Partner NCC is smeared a few lines past a photo's edge (band-pass blur, coarse sampling):
    # the foreign lines are looked for beyond a gap of g lines from the edge.
    g = max(k, n // 60)
    limit = min(n - k - 1, int(params.max_border * n), n if max_width is None else max_width)
    if limit <= k + g:
        return 0
    positions = np.arange(k + g, limit + 1)  # a border of width y: lines [0, y) are outside
    change = (np.abs(lines[positions + k - 1] - lines[positions - k]) > params.edge_threshold).mean(axis=1)
    plain, partnerless = textured.mean(axis=1) <= _PLAIN, matched < _MATCHED
    # A column across the middle rows of a photo is never plain, so a plain column is foreign
    # even if it seems to match (band-pass smear from a nearby photo edge); a row can be plain
    # inside a photo (sky, water, a road), so a row is foreign only if it is also partnerless.
    foreign = (plain | partnerless) if columns else (plain & partnerless)
    cum = np.concatenate(([0.0], np.cumsum(foreign)))
    outside = cum[positions - g] / (positions - g)
    # Right outside the edge, lines must be plain as well: a printed title leaves plain mount
    # beside the photo, while a view's extra strip (scenery the other eye does not see) is
    # partnerless but textured, and belongs to the photo.
    near = np.concatenate(([0.0], np.cumsum(foreign & plain)))
    just_outside = (near[positions - g] - near[positions - g - k]) / k
    fraction = params.edge_fraction if columns else params.row_edge_fraction
    ok = (change >= fraction) & (just_outside >= 1.0) & (outside >= 0.5)
    runs = _runs(ok)
    if not runs:
        return 0
    start, end = runs[-1]  # the innermost edge, placed where the change peaks
    return int(positions[start + int(np.argmax(change[start:end]))])


def _photo_box(an: _Analysis, x0: int, x1: int, column_match: np.ndarray, left: bool, params: SplitParams) -> Box:
    """Photo extent (analysis px) inside columns ``[x0, x1)``: the half minus its borders.

    Vertical edges are looked for in the middle half of the rows and horizontal edges in the
    middle half of the photo's columns: photos sit in the middle of a card, and the mount above
    and below a photo (or an arched top) would dilute its edges.
    """
    grey, tex = an.smooth[:, x0:x1], an.textured[:, x0:x1]
    height, width = grey.shape
    mid = slice(height // 4, max(height // 4 + 1, 3 * height // 4))
    cols, cols_tex, match = grey[mid].T, tex[mid].T, column_match[x0:x1]
    # Side titles are printed on the outer borders; between the photos there is plain mount.
    # So only the outer side may treat partnerless columns as foreign: near the gutter, content
    # whose disparity exceeds the search (a close foreground) must not pass for a border.
    # The gutter side is trimmed by at most 2 % of the card width (half a wide gutter): plain
    # photo columns there (mist, sky) next to a vertical structure would otherwise pass for mount.
    inner, inner_max = np.ones_like(match), max(2, round(0.02 * an.smooth.shape[1]))
    if left:
        c0 = _border(cols, cols_tex, match, True, params)
        c1 = width - _border(cols[::-1], cols_tex[::-1], inner, True, params, inner_max)
    else:
        c0 = _border(cols, cols_tex, inner, True, params, inner_max)
        c1 = width - _border(cols[::-1], cols_tex[::-1], match[::-1], True, params)
    if c1 - c0 < 2:
        c0, c1 = 0, width

    # Rows and their partners are judged on the middle half of the photo's columns, away from
    # film edges and gutters whose strong vertical lines would dominate every row.
    quarter = (c1 - c0) // 4
    m0, m1 = x0 + c0 + quarter, x0 + c1 - quarter
    if not left:
        m0, m1 = m0 - _analysis_period(an), m1 - _analysis_period(an)  # the left photo's columns
    c_scale = an.band.shape[1] / an.smooth.shape[1]
    rows_match = _row_similarity(
        an.band, max(0, int(m0 * c_scale)), max(1, int(np.ceil(m1 * c_scale))), an.period, an.dy, an.tolerance
    )
    if not left and an.dy:  # the right photo's rows are dy lower
        shifted = np.zeros_like(rows_match)
        if an.dy > 0:
            shifted[an.dy :] = rows_match[: -an.dy]
        else:
            shifted[: an.dy] = rows_match[-an.dy :]
        rows_match = shifted
    rows_match = _resample(rows_match, height)
    rows, rows_tex = grey[:, c0 + quarter : c1 - quarter], tex[:, c0 + quarter : c1 - quarter]
    r0 = _border(rows, rows_tex, rows_match, False, params)
    r1 = height - _border(rows[::-1], rows_tex[::-1], rows_match[::-1], False, params)
    if r1 - r0 < 2:
        r0, r1 = 0, height
    return x0 + c0, r0, x0 + c1, r1


def _analysis_period(an: _Analysis) -> int:
    return round(an.period * an.smooth.shape[1] / an.band.shape[1])


def _place(center: float, size: int, lo: int, hi: int) -> tuple[int, int]:
    """An interval of ``size`` centred near ``center``, shifted to lie inside ``[lo, hi)``."""
    start = min(max(round(center - size / 2), lo), hi - size)
    return start, start + size


def _equalise(left: Box, right: Box, gutter: int, width: int, height: int) -> tuple[Box, Box]:
    """Give both boxes the larger width and height, limited to what fits in each half."""
    box_w = min(max(left[2] - left[0], right[2] - right[0]), gutter, width - gutter)
    box_h = min(max(left[3] - left[1], right[3] - right[1]), height)
    boxes = []
    for (x0, y0, x1, y1), (lo, hi) in ((left, (0, gutter)), (right, (gutter, width))):
        bx0, bx1 = _place((x0 + x1) / 2, box_w, lo, hi)
        by0, by1 = _place((y0 + y1) / 2, box_h, 0, height)
        boxes.append((bx0, by0, bx1, by1))
    return boxes[0], boxes[1]


# ------------------------------------------------------------------------------------- API


def split_card(card: np.ndarray, params: SplitParams = SplitParams()) -> CardSplit:
    """Split a stereo card into its left and right photo.

    ``card``: uint8 ``(H, W)`` grey or ``(H, W, 3)`` RGB, at least 32 x 16 px (else
    :class:`InvalidInputError`). Returns the gutter column and two equal-size boxes in card
    pixels. Never raises for a valid array: a card with no evidence at all (blank) is split in
    the middle with ``method="centre"`` and confidence 0. See the module docstring.
    """
    check_card(card)
    height, width = card.shape[:2]
    an = _analyse(card, params)
    a_width = an.smooth.shape[1]
    best, method, confidence = _choose_split(an, params)

    boxes_a = (
        _photo_box(an, 0, best, an.fwd, True, params),
        _photo_box(an, best, a_width, an.bwd, False, params),
    )
    gutter_x = int(np.clip(round(best * an.scale), 1, width - 1))
    pad = params.margin * width
    boxes = []
    for (x0, y0, x1, y1), (lo, hi) in zip(boxes_a, ((0, gutter_x), (gutter_x, width))):
        boxes.append(
            (
                int(np.clip(np.floor(x0 * an.scale - pad), lo, hi - 1)),
                int(np.clip(np.floor(y0 * an.scale - pad), 0, height - 1)),
                int(np.clip(np.ceil(x1 * an.scale + pad), lo + 1, hi)),
                int(np.clip(np.ceil(y1 * an.scale + pad), 1, height)),
            )
        )
    left_box, right_box = _equalise(boxes[0], boxes[1], gutter_x, width, height)
    return CardSplit(left_box=left_box, right_box=right_box, gutter_x=gutter_x, method=method, confidence=confidence)


def scale_split(split: CardSplit, factor: int, full_size: tuple[int, int]) -> CardSplit:
    """``split`` found on a card decoded at ``1 / factor`` (:func:`pipeline.io.read_image_reduced`)
    in the full card's pixels ``full_size`` = (W, H): every coordinate times ``factor``. A box that
    would end past the card is moved back inside (not shrunk), so the two boxes keep one size."""
    width, height = full_size
    gutter_x = int(np.clip(split.gutter_x * factor, 1, width - 1))

    def scaled(box: Box) -> Box:
        x0, y0, x1, y1 = (v * factor for v in box)
        shift_x, shift_y = max(0, x1 - width), max(0, y1 - height)
        return (max(0, x0 - shift_x), max(0, y0 - shift_y), x1 - shift_x, y1 - shift_y)

    return CardSplit(
        left_box=scaled(split.left_box),
        right_box=scaled(split.right_box),
        gutter_x=gutter_x,
        method=split.method,
        confidence=split.confidence,
    )


def crop_halves(card: np.ndarray, split: CardSplit) -> tuple[np.ndarray, np.ndarray]:
    """The two photos as views into ``card`` (no copy): ``card[y0:y1, x0:x1]`` for each box."""
    height, width = card.shape[:2]
    halves = []
    for name, (x0, y0, x1, y1) in (("left_box", split.left_box), ("right_box", split.right_box)):
        if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
            raise InvalidInputError(f"Expected {name} inside the {width}x{height} card, got {(x0, y0, x1, y1)}")
        halves.append(card[y0:y1, x0:x1])
    return halves[0], halves[1]
