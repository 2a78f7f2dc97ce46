"""Find each photo inside its mount and propose the largest artifact-free crop box per half.

:func:`pipeline.split.split_card` finds the gutter and boxes each half conservatively: its
boxes often keep printed side titles, captions, arch corners, card edges and, on raw scans,
film edges. This module looks inside each half of the split for the photograph itself.

Method, on a copy downscaled (area filter) to ``working_width`` ("working px"):

1. **Mount colour.** Ring pixels just inside the card's edge (``mount_ring``, fractions of the
   card's smaller side) within ``mount_sample_distance`` (CIE Lab) of the ring's most populated
   Lab bin sample the mount. It counts as a mount only if it covers ``mount_coverage`` of three
   of the ring's four sides (a sky along one side of an unmounted photo is no mount). Mounts are
   shaded and stained unevenly, so the mount colour is a quadratic surface over the card,
   fitted to those samples. The lit ring pixels are tried first (a dark scan background often
   fills part of the ring), then the not-white ones (a negative), then all (a black mount).
2. **Non-photo mask.** *Plain* pixels are: of the mount's colour (within ``mount_distance`` and
   smooth - 5 x 5 grey spread below ``smooth_spread`` - or within ``mount_exact``, as between
   the letters of a title), dark and smooth (film edges, black mounts, scan background), or
   white and smooth (white margins). A photo's content can look like mount (a pale sky, sepia
   ground), so plain pixels count only in regions that reach the card's frame without crossing
   an edge (Canny, plus long horizontal and vertical Hough segments bridged over faint stretches
   of a photo's straight edge) and span half the card's width or height. Mount-coloured pieces
   next to those regions join them (between the letters of a title); columns dark or white down
   nearly the whole card are film edges or separator lines; a closing (``text_closing``)
   absorbs printed text and the edges themselves.
3. **Largest rectangle.** Inside each half of the split, the mask is pooled onto cells (at least
   ``cell`` working px, at most 64 a side; a cell is non-photo when half of it is, or when a
   film-edge line crosses it) and the largest rectangle of photo cells is found (histogram
   method, O(cells)). Under an arched top that rectangle reaches up into the arch, narrower than
   the photo; the photo's full width is preferred when it keeps ``full_width_preference`` of the
   area (the box then starts where the arch meets the sides). The edges are refined in working
   px (out while the next line is clean, in while the border line is not), then the box is cut
   at *straight edges* near its sides: lines where most pixels change the same way, with a
   foreign strip (non-photo or plain) outside them - a caption band, a film edge, a wedge - or
   with whatever lies beyond when the line rules nearly the whole side (``ruled_edge``: a film
   edge next to the other frame's picture, a caption band's top). A *uniform band* along a side
   (lines each of nearly one colour, then a photo's texture: a window mount's gold frame, a
   gutter strip) is cut off too.
4. **Safety.** The search runs on the card as it is and turned by 180 degrees (it is not
   symmetric: cell grid, tie-breaks, the arch rule) and keeps what both agree is photo. Under
   an arch (the photo narrows above the box, or only the box's very corners are mount) the box
   starts ``arch_inset`` of its height lower: the arch meets the photo's sides lower than the
   box's corners show. The evidence names it: ``arched top`` when the photo narrows across its
   outer sixths and the mount beside the narrowing is bare card on at least one side (80 % of
   its pixels plain; the orientation step reads only these as arches), ``uneven top edge`` when
   it narrows but beside it is texture (dark foliage or a pale sky taken for mount), ``rounded
   top corners`` when only the very corners are mount. No non-photo pixel may lie on a side's
   outer line near a corner (``corner``). Printed text beside or across a side (ink words on
   plain or non-photo ground, such as a collection stamp running onto the photo's margin) pushes
   that side past it.
5. **Consistency.** Both boxes get the rows the two share (the intersection lies inside both
   photo areas; a pair's photos are mounted level), keep their own widths (the crop stage
   aligns by SIFT and cuts both to their intersection anyway), are inset by ``inset`` (fraction
   of the card width: a photo's edge is blurred, and the rules above are evidence, not proof)
   and are mapped back to card pixels, rounding inwards.

Measured (``python -m benchmarks.photo_area --variants``; 11 real cards, all seen while tuning):
every box strictly inside the hand-drawn photo on the cards as scanned, turned 180 degrees and
at 200 %, 21 of 22 at 50 % (22 within 2 px), 17 of 22 as negatives; mean IoU 0.76; about
0.05 s CPU per card.

What was found is said in words in :attr:`PhotoAreas.evidence`. When nothing trustworthy is
found (a blank card, no border at all, two photos in one half, halves sharing too few rows, no
gutter),
the result falls back to the split's boxes, says why in ``fallback_reason`` and has a
confidence of at most ``fallback_confidence``: never a silent guess.

A crop task asks for the whole photo, not a safe part of it: :func:`grow_to_photo_edges` grows
boxes (these, or others) back out to the photos' edges over the same non-photo mask, stopping at
a straight edge (mean IoU with the demo cards' prints 0.68 -> 0.93, with the hand-drawn boxes
above 0.76 -> 0.86; about 0.05 s CPU a card).

Conventions: cards are ``uint8`` or ``uint16`` arrays, ``(H, W)`` grey or ``(H, W, 3)`` RGB
(16-bit is stretched to its used range, as :func:`pipeline.io.read_image` does). Boxes are
``(x0, y0, x1, y1)`` in the card's pixels, ``x1``/``y1`` exclusive; the left box lies in
``[0, gutter_x)`` and the right one in ``[gutter_x, W)`` of the split.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from .errors import InvalidInputError
from .split import MIN_HEIGHT, MIN_WIDTH, CardSplit, SplitParams, check_card, split_card

Box = tuple[int, int, int, int]


@dataclass(frozen=True)
class PhotoAreaParams:
    """Parameters of :func:`find_photo_areas`. Grey levels are 0..255; Lab distances are CIE76."""

    working_width: int = 480
    """px: the card is downscaled (area filter) to at most this width for all analysis."""
    mount_ring: tuple[float, float] = (0.02, 0.07)
    """The mount colour is sampled between these insets from the card's edge (fractions of the
    card's smaller side): inside the scan background, outside most photos."""
    mount_distance: float = 10.0
    """Lab distance to the fitted mount colour below which a pixel has the mount's colour."""
    mount_exact: float = 6.0
    """Lab distance below which a pixel is mount even where it is not smooth (between letters)."""
    mount_sample_distance: float = 20.0
    """Ring pixels within this Lab distance of the ring's dominant colour sample the mount."""
    mount_coverage: float = 0.6
    """Fraction of a ring side that the mount colour must cover, on three of the four sides."""
    smooth_spread: float = 8.0
    """Grey levels: a local standard deviation below this makes a pixel smooth."""
    dark_level: float = 60.0
    """Grey level below which a smooth pixel is film edge, black mount or scan background."""
    white_level: float = 252.0
    """Grey level above which a smooth pixel is a white margin (skies stay below: 245-250)."""
    edge_low: int = 20
    edge_high: int = 50
    """Canny thresholds (grey levels, after a 1 px Gaussian): plain regions do not cross edges."""
    line_fraction: float = 0.9
    """A column darker than ``dark_level`` (or brighter than ``white_line_level``) over this
    fraction of the card's height is a film edge or separator line."""
    white_line_level: float = 235.0
    straight_edge: float = 0.6
    """Fraction of a box's row (column) whose pixels change by more than ``edge_step`` across it
    for a straight edge: a caption band's top, a film edge, a wedge's side. Natural edges inside
    a photo are ragged (measured on the real cards: 0.3-0.7)."""
    edge_step: float = 10.0
    """Grey levels: a pixel changes across a straight edge if it differs by more than this."""
    foreign_strip: float = 0.3
    """A straight edge is cut at only if at least this fraction of the strip outside it is
    non-photo or plain (spread below ``plain_spread``): a caption band, a title, a film edge."""
    plain_spread: float = 5.0
    band_depth: float = 0.05
    band_spread: float = 9.0
    band_contrast: float = 1.5
    """A uniform band along a box's side (a frame, a gutter strip) is cut off: at most
    ``band_depth`` of the box's size of lines, typically within ``band_spread`` (mean CIE76) of
    their own median colour, followed by lines ``band_contrast`` times less uniform."""
    ruled_edge: float = 0.9
    """Fraction of a box's row (column) changing the same way for a straight edge that is cut at
    whatever lies beyond it (film edges, frames, separators; scenes rarely rule a whole side)."""
    edge_band: float = 0.15
    """Straight edges are looked for within this fraction of the box's height (width) of each side."""
    edge_passes: int = 1
    """Straight-edge cuts are repeated (on the cut box) up to this many times."""
    full_width_preference: float = 0.8
    """A rectangle spanning the photo's full width is preferred to the largest rectangle if its
    area is at least this fraction of the largest one (arched tops: the box starts where the arch
    meets the sides)."""
    barrier_length: float = 0.15
    barrier_gap: float = 0.08
    """Straight segments of at least ``barrier_length`` of the card width, bridged over gaps of
    ``barrier_gap``, are barriers to the mount's flood (fractions of the working width)."""
    min_span: float = 0.5
    """A plain region counts as mount, strip or margin only if it spans this fraction of the
    card's width or height."""
    text_closing: float = 0.02
    """Closing of the non-photo mask (fraction of the working width) that absorbs printed text."""
    cell: int = 3
    """Working px per cell of the largest-rectangle search, at least (larger halves get larger
    cells: at most 64 a side)."""
    clean_line: float = 0.01
    """A line (row or column) with at most this non-photo fraction is clean (edge refinement)."""
    corner: float = 0.08
    """Near each corner of a box (this fraction of its width or height from the corner) a side's
    outer line must hold no non-photo pixel: arch corners, rounded windows."""
    arch_inset: float = 0.05
    """Under an arched top (bottom) the box starts this fraction of its height lower (ends higher)."""
    text_clearance: float = 0.005
    """Boxes keep this fraction of the card's width away from printed text on the mount beside them."""
    ink_contrast: float = 40.0
    """Grey levels: a stroke this much darker (lighter) than its surroundings is ink."""
    text_background: float = 0.45
    """Ink is text when at least this fraction of its word's surroundings is plain or non-photo."""
    inset: float = 0.014
    """Each box is inset by this fraction of the card width: a photo's edge is blurred."""
    min_area: float = 0.2
    """A box smaller than this fraction of its half is not believed (fallback)."""
    min_agreement: float = 0.5
    """Boxes whose widths or heights differ more than this ratio are not believed (fallback)."""
    fallback_confidence: float = 0.2
    """Upper bound of the confidence of a fallback result."""
    split: SplitParams = field(default_factory=SplitParams)

    def __post_init__(self) -> None:
        if self.working_width < MIN_WIDTH:
            raise InvalidInputError(f"Expected working_width >= {MIN_WIDTH} px, got {self.working_width}")
        low, high = self.mount_ring
        if not 0.0 <= low < high <= 0.5:
            raise InvalidInputError(f"Expected 0 <= mount_ring[0] < mount_ring[1] <= 0.5, got {self.mount_ring}")
        if self.cell < 1:
            raise InvalidInputError(f"Expected cell >= 1 px, got {self.cell}")
        for name in ("mount_coverage", "text_closing", "clean_line", "inset", "min_area", "min_agreement", "fallback_confidence"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InvalidInputError(f"Expected 0 <= {name} <= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class PhotoAreas:
    """The photo area of each half of a card."""

    left_box: Box  # (x0, y0, x1, y1) in card pixels, x1/y1 exclusive
    right_box: Box
    gutter_x: int  # the split's column: left_box ends at or before it, right_box starts at or after
    confidence: float  # 0..1
    evidence: tuple[str, ...]  # what was found, in words
    fallback_reason: str | None  # why the split's boxes were kept; None when the photo areas are used
    split: CardSplit  # the split the boxes lie in

    @property
    def is_fallback(self) -> bool:
        return self.fallback_reason is not None


def as_card(image: np.ndarray) -> np.ndarray:
    """A ``uint8`` card from a ``uint8`` or ``uint16`` array (16-bit stretched to its used
    range); raises :class:`InvalidInputError` for other dtypes, shapes or sizes."""
    if isinstance(image, np.ndarray) and image.dtype == np.uint16:
        lo, hi = int(image.min()), int(image.max())
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        image = np.clip(np.rint((image.astype(np.float32) - lo) * scale), 0, 255).astype(np.uint8)
    check_card(image)
    return image


# ------------------------------------------------------------------------------- the mask


@dataclass
class _Mask:
    """Working-scale measurements (``(h, w)`` arrays)."""

    scale_x: float  # card px per working px
    scale_y: float
    grey: np.ndarray  # float32 grey levels
    non_photo: np.ndarray  # bool: mount, text, film edge, margin
    foreign: np.ndarray  # bool: non-photo or very plain (what lies outside a photo's straight edge)
    line_columns: np.ndarray  # (w,) bool: film edge or separator line down the whole card
    plain: np.ndarray  # bool: mount-coloured, dark or white plain pixels, before the flood
    mount: np.ndarray  # bool: smooth pixels of the mount colour (before closing)
    dark: np.ndarray  # bool: smooth and dark
    white: np.ndarray  # bool: smooth and white
    mount_rgb: tuple[int, int, int] | None  # mount colour, None when there is no mount
    lab: np.ndarray  # (h, w, 3) float32 CIE Lab


def _working_copy(card: np.ndarray, width: int) -> np.ndarray:
    height, current = card.shape[:2]
    if current <= width:
        return card
    return cv2.resize(card, (width, max(MIN_HEIGHT, round(height * width / current))), interpolation=cv2.INTER_AREA)


def _quadratic_terms(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``(n, 6)`` design matrix of a quadratic surface in normalised coordinates."""
    return np.stack([np.ones_like(x), x, y, x * x, y * y, x * y], axis=1)


def _mount_colour(lab: np.ndarray, grey: np.ndarray, params: PhotoAreaParams) -> np.ndarray | None:
    """``(h, w, 3)`` Lab colour the mount would have at each pixel, or None when the card has no
    mount: see step 1 of the module docstring. Mounts are shaded and stained unevenly (a darker
    corner, a faded side), so the colour is a quadratic surface fitted to the ring pixels near the
    dominant colour. Dark pixels (scan background, black film edges) have a cue of their own."""
    height, width = lab.shape[:2]
    side = min(height, width)
    a, b = max(1, round(params.mount_ring[0] * side)), max(2, round(params.mount_ring[1] * side))
    ring_mask = np.zeros((height, width), bool)
    ring_mask[a : height - a, a : width - a] = True
    ring_mask[b : height - b, b : width - b] = False
    ys, xs = np.nonzero(ring_mask)
    if ys.size > 6000:  # plenty for a 6-parameter fit; keeps the cost flat
        step = ys.size // 6000 + 1
        ys, xs = ys[::step], xs[::step]
    if ys.size < 16:
        return None
    level = grey[ys, xs]
    # The mount's colour is looked for among the lit ring pixels first (a dark scan background
    # often fills part of the ring), then among the not-white ones (the scan background of a
    # negative is white), then among all (a black mount).
    for chosen in (level >= params.dark_level, level <= 255 - params.dark_level, np.ones_like(level, bool)):
        if chosen.sum() < 16:
            continue
        ys_c, xs_c = ys[chosen], xs[chosen]
        ring = lab[ys_c, xs_c].astype(np.float64)
        # Dominant colour: the most populated Lab bin (8 x 6 x 6 units), by a 1-D key.
        bins = np.floor(ring / np.array([8.0, 6.0, 6.0])).astype(np.int64) + np.array([0, 32, 32])
        keys = (np.clip(bins[:, 0], 0, 63) * 64 + np.clip(bins[:, 1], 0, 63)) * 64 + np.clip(bins[:, 2], 0, 63)
        mode = int(np.argmax(np.bincount(keys)))
        centre = (np.array([mode // 4096, (mode // 64) % 64 - 32, mode % 64 - 32]) + 0.5) * np.array([8.0, 6.0, 6.0])
        near = np.linalg.norm(ring - centre, axis=1) < params.mount_sample_distance
        # The mount must surround the photos: seen on three of the ring's four sides.
        sides = [ys_c < b, ys_c >= height - b, xs_c < b, xs_c >= width - b]
        if near.sum() >= 16 and sum(float(near[s].mean()) >= params.mount_coverage for s in sides if s.any()) >= 3:
            break
    else:
        return None
    ys, xs = ys_c, xs_c
    design = _quadratic_terms(xs / width - 0.5, ys / height - 0.5)
    keep = near
    for _ in range(2):  # refit without the outliers (text, stains) of the first fit
        d = design[keep]
        # Normal equations of a 6-parameter fit (a small solve; lstsq's SVD costs 10x more).
        coefficients = np.linalg.solve(d.T @ d + 1e-9 * np.eye(6), d.T @ ring[keep])
        residual = np.linalg.norm(design @ coefficients - ring, axis=1)
        keep = near & (residual < max(params.mount_distance, 2.5 * float(np.median(residual[keep]))))
    x = (np.arange(width) / width - 0.5)[None, :, None]
    y = (np.arange(height) / height - 0.5)[:, None, None]
    c = coefficients.astype(np.float32)  # (6, 3): 1, x, y, x^2, y^2, xy
    field = c[0] + x * c[1] + y * c[2] + x * x * c[3] + y * y * c[4] + x * y * c[5]
    return field.astype(np.float32)


def _measure(card: np.ndarray, params: PhotoAreaParams) -> _Mask:
    small = _working_copy(card, params.working_width)
    rgb = small if small.ndim == 3 else cv2.cvtColor(small, cv2.COLOR_GRAY2RGB)
    grey_u8 = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    grey = grey_u8.astype(np.float32)
    lab = cv2.cvtColor(rgb.astype(np.float32) / 255.0, cv2.COLOR_RGB2LAB)  # L 0..100, a/b about -128..127
    mean = cv2.blur(grey, (5, 5))
    spread = np.sqrt(np.maximum(cv2.blur(grey * grey, (5, 5)) - mean * mean, 0.0))
    smooth = spread < params.smooth_spread
    colour = _mount_colour(lab, grey, params)
    mount_rgb: tuple[int, int, int] | None = None
    if colour is None:
        mount = np.zeros(grey.shape, bool)
    else:
        distance = np.linalg.norm(lab - colour, axis=2)
        # Between the strokes of printed titles the mount is not smooth, but exactly its colour.
        mount = (smooth & (distance < params.mount_distance)) | (distance < params.mount_exact)
        typical = np.median(colour.reshape(-1, 3), axis=0)
        pixel = cv2.cvtColor(typical.astype(np.float32).reshape(1, 1, 3), cv2.COLOR_LAB2RGB).reshape(3)
        red, green, blue = (int(v) for v in np.clip(np.rint(pixel * 255.0), 0, 255))
        mount_rgb = (red, green, blue)
    dark = smooth & (mean < params.dark_level)
    white = smooth & (mean > params.white_level)

    # A photo's edge is a line of strong gradient; a mount-coloured patch inside a photo (a pale
    # sky, sepia ground) is cut off from the mount by it. So plain pixels count only if they are
    # connected, without crossing an edge, to the frame of the card (where mount, film edge and
    # scan background are) and spread along a good part of a side (a margin, a strip, a mount).
    edges = cv2.Canny(cv2.GaussianBlur(grey_u8, (0, 0), 1.0), params.edge_low, params.edge_high)
    # A photo's edge is straight; where the picture fades into the mount's colour (a pale sky,
    # sepia ground) the edge map has gaps. Long horizontal and vertical segments, bridged over
    # such gaps, become barriers too.
    height, width = grey.shape
    segments = cv2.HoughLinesP(
        edges,
        1,
        np.pi / 180,
        threshold=max(8, round(0.1 * width)),
        minLineLength=max(8, round(params.barrier_length * width)),
        maxLineGap=max(2, round(params.barrier_gap * width)),
    )
    for xa, ya, xb, yb in np.zeros((0, 4), int) if segments is None else segments.reshape(-1, 4):
        if abs(int(xa) - int(xb)) <= 2 or abs(int(ya) - int(yb)) <= 2:
            cv2.line(edges, (int(xa), int(ya)), (int(xb), int(yb)), 255, 1)
    is_edge = edges > 0
    plain = (mount | dark | white) & ~is_edge
    count, labels, stats, _ = cv2.connectedComponentsWithStats(plain.astype(np.uint8), connectivity=4)
    frame = max(2, round(params.mount_ring[1] * min(height, width)))
    seeds = np.zeros((height, width), bool)
    seeds[:frame], seeds[-frame:], seeds[:, :frame], seeds[:, -frame:] = True, True, True, True
    seeded = np.bincount(labels[seeds], minlength=count) > 0
    span = (stats[:, cv2.CC_STAT_WIDTH] >= params.min_span * width) | (stats[:, cv2.CC_STAT_HEIGHT] >= params.min_span * height)
    keep = seeded & span
    keep[0] = False  # label 0: not plain
    raw = keep[labels]
    # Between the letters of a printed title the mount is cut into small pieces by the letters'
    # edges; pieces of the mount's colour next to the kept mount join it (twice: titles are wide).
    k = max(3, round(params.text_closing * small.shape[1])) | 1
    for _ in range(2):
        near = cv2.dilate(raw.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        raw = raw | (near & mount)
    # Thin film edges and separator lines (a few working px) are neither smooth nor plain, but
    # they run dark (or white) down nearly the whole card, which a photo's column never does.
    dark_column = (grey < params.dark_level).mean(axis=0) >= params.line_fraction
    white_column = (grey > params.white_line_level).mean(axis=0) >= params.line_fraction
    line_columns = dark_column | white_column
    raw[:, line_columns] = True
    dark |= dark_column[None, :]
    white |= white_column[None, :]
    raw = raw.astype(np.uint8)
    # Printed text and the edge pixels themselves sit between kept plain pixels: a closing
    # absorbs them.
    non_photo = cv2.morphologyEx(raw, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return _Mask(
        scale_x=card.shape[1] / small.shape[1],
        scale_y=card.shape[0] / small.shape[0],
        grey=grey,
        non_photo=non_photo.astype(bool),
        line_columns=line_columns,
        plain=mount | dark | white,
        foreign=non_photo.astype(bool) | (spread < params.plain_spread),
        mount=mount & raw.astype(bool),
        dark=dark & raw.astype(bool),
        white=white & raw.astype(bool),
        mount_rgb=mount_rgb,
        lab=lab,
    )


# ---------------------------------------------------------------------- largest rectangle


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` of each run of True in a 1-D boolean array."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _largest_rectangle(good: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(r0, c0, r1, c1)`` (exclusive ends) of the largest all-True rectangle of a 2-D bool
    array, or None if it has no True cell. Histogram method: per row, the run heights above it
    and the largest rectangle under that histogram (stack), O(rows x columns)."""
    rows, cols = good.shape
    heights = np.zeros(cols, np.int64)
    best, best_area = None, 0
    for r in range(rows):
        heights = np.where(good[r], heights + 1, 0)
        hs = heights.tolist() + [0]
        stack: list[int] = []
        for c, h in enumerate(hs):
            start = c
            while stack and hs[stack[-1]] >= h:
                top = stack.pop()
                left = stack[-1] + 1 if stack else 0
                area = hs[top] * (c - left)
                if area > best_area:
                    best_area, best = area, (r + 1 - hs[top], left, r + 1, c)
                start = left
            stack.append(c)
            del start
    return best


def _refine(bad: np.ndarray, box: tuple[int, int, int, int], clean: float, steps: int) -> tuple[int, int, int, int]:
    """Move each edge of ``box`` (``(y0, x0, y1, x1)`` in ``bad``'s px) out while the next line
    is clean and in while its border line is not (at most ``steps`` px either way)."""
    y0, x0, y1, x1 = box
    height, width = bad.shape
    for _ in range(steps):
        moved = False
        if y0 > 0 and bad[y0 - 1, x0:x1].mean() <= clean:
            y0, moved = y0 - 1, True
        if y1 < height and bad[y1, x0:x1].mean() <= clean:
            y1, moved = y1 + 1, True
        if x0 > 0 and bad[y0:y1, x0 - 1].mean() <= clean:
            x0, moved = x0 - 1, True
        if x1 < width and bad[y0:y1, x1].mean() <= clean:
            x1, moved = x1 + 1, True
        if not moved:
            break
    for _ in range(steps):
        moved = False
        if y1 - y0 > 2 and bad[y0, x0:x1].mean() > clean:
            y0, moved = y0 + 1, True
        if y1 - y0 > 2 and bad[y1 - 1, x0:x1].mean() > clean:
            y1, moved = y1 - 1, True
        if x1 - x0 > 2 and bad[y0:y1, x0].mean() > clean:
            x0, moved = x0 + 1, True
        if x1 - x0 > 2 and bad[y0:y1, x1 - 1].mean() > clean:
            x1, moved = x1 - 1, True
        if not moved:
            break
    return y0, x0, y1, x1


def _prefer_full_width(
    good: np.ndarray,
    best: tuple[int, int, int, int],
    preference: float,
) -> tuple[int, int, int, int]:
    """Under an arched top the largest rectangle is narrower than the photo and reaches up into
    the arch. The photo's full width is where the lower half of ``best``'s rows is photo in every
    column; the rectangle of that width reaching as high as the columns allow is returned if its
    area is at least ``preference`` of ``best``'s, else ``best``. Rectangles are ``(r0, c0, r1, c1)``."""
    r0, c0, r1, c1 = best
    middle = (r0 + r1) // 2
    lower = np.asarray(good[middle:r1].all(axis=0))
    left, right = c0, c1
    while left > 0 and lower[left - 1]:
        left -= 1
    while right < lower.size and lower[right]:
        right += 1
    if right - left < 1.05 * (c1 - c0) + 1:  # a cell or two wider is no arch
        return best
    full = np.asarray(good[:r1, left:right].all(axis=1))
    top = middle
    while top > 0 and full[top - 1]:
        top -= 1
    if (right - left) * (r1 - top) >= preference * (c1 - c0) * (r1 - r0):
        return top, left, r1, right
    return best


def _cut_straight_edges(
    grey: np.ndarray,
    foreign: np.ndarray,
    box: tuple[int, int, int, int],
    params: PhotoAreaParams,
    sides: set[str],
) -> tuple[int, int, int, int, list[str]]:
    """Cut ``box`` (``(y0, x0, y1, x1)``, ``grey``'s px) at straight edges near its sides.

    A straight edge is a line across the box where at least ``straight_edge`` of the pixels
    change by more than ``edge_step`` (comparing 2 px either side): the top of a caption band,
    a film edge, a wedge. Scenes have straight lines too (shelves, roofs, a horizon), so an edge
    only counts if the strip it cuts off looks foreign: ``foreign`` (non-photo or very plain
    pixels) covers at least ``foreign_strip`` of it. The innermost such edge within
    ``edge_band`` of a side becomes that side (only for the named ``sides``).
    """
    y0, x0, y1, x1 = box
    cuts = []
    k = 2
    for axis in ("rows", "columns"):
        lines = grey[y0:y1, x0:x1] if axis == "rows" else grey[y0:y1, x0:x1].T
        alien = foreign[y0:y1, x0:x1] if axis == "rows" else foreign[y0:y1, x0:x1].T
        n = lines.shape[0]
        if n < 4 * k + 4:
            continue
        # Smoothed along the line, a straight edge stays and texture fades; and across a straight
        # edge the pixels change the same way (a band is darker or lighter all along).
        along = cv2.blur(np.ascontiguousarray(lines), (9, 1))
        step = along[2 * k :] - along[: -2 * k]
        change = np.maximum(
            (step > params.edge_step).mean(axis=1), (step < -params.edge_step).mean(axis=1)
        )  # [i]: edge at line i + k
        reach = max(k + 1, int(params.edge_band * n))
        per_line = np.concatenate(([0.0], np.cumsum(alien.mean(axis=1))))  # [j]: sum over lines [0, j)
        edge_line = np.arange(change.size) + k  # the line each change value sits on
        outside_start = per_line[edge_line] / np.maximum(edge_line, 1)  # strip [0, edge)
        outside_end = (per_line[n] - per_line[edge_line + 1]) / np.maximum(n - edge_line - 1, 1)  # strip (edge, n)
        straight = change >= params.straight_edge
        # A line that changes the same way along nearly the whole side (a film edge, a frame's
        # inner edge, a separator) is cut at whatever lies beyond it.
        # Not the photo's own (blurred) edge where the box already sits on it: such a line has a
        # strip beyond it at least ``2 k`` lines wide.
        ruled = change >= params.ruled_edge
        index = np.arange(change.size)
        ruled_start, ruled_end = ruled & (index >= 2 * k), ruled & (index + 4 * k <= n - 1)
        start_hits = np.flatnonzero((ruled_start | (straight & (outside_start >= params.foreign_strip)))[: reach - k])
        first_end = max(0, n - reach - k)
        end_hits = np.flatnonzero((ruled_end | (straight & (outside_end >= params.foreign_strip)))[first_end:]) + first_end
        lo, hi = 0, n
        first, last = ("top", "bottom") if axis == "rows" else ("left", "right")
        if start_hits.size and first in sides:
            lo = int(start_hits.max()) + 2 * k + 1  # past the edge and its blur
        if end_hits.size and last in sides:
            hi = int(end_hits.min())
        if hi - lo < n // 2:  # never cut a box in half
            continue
        if axis == "rows":
            if lo:
                cuts.append("top")
            if hi < n:
                cuts.append("bottom")
            y0, y1 = y0 + lo, y0 + hi
        else:
            if lo:
                cuts.append("left")
            if hi < n:
                cuts.append("right")
            x0, x1 = x0 + lo, x0 + hi
    return y0, x0, y1, x1, cuts


def _cut_uniform_bands(
    lab: np.ndarray,
    box: tuple[int, int, int, int],
    params: PhotoAreaParams,
) -> tuple[int, int, int, int, list[str]]:
    """Cut ``box`` (``(y0, x0, y1, x1)``, ``lab``'s px) inside a uniform band along a side.

    A window mount's frame (gold foil), a gutter strip, a photo's printed margin: lines parallel
    to the side, each of nearly one colour along its length (mean CIE76 distance to its median
    below ``band_spread``, as a median over the band), from the box's side inwards, then lines
    of a photo's texture (their spread ``band_contrast`` times the band's). Its edge is soft at the working scale (a few px
    of blur), which a straight-edge test misses. A sky is uniform along the top lines too but
    then goes on uniform, or turns to texture gradually; at worst ``band_depth`` of the box is
    lost. The middle 80 % of each line is used (a frame's rounded corners)."""
    y0, x0, y1, x1 = box
    cuts = []
    for side in ("top", "bottom", "left", "right"):
        region = lab[y0:y1, x0:x1]
        lines = {
            "top": region,
            "bottom": region[::-1],
            "left": region.transpose(1, 0, 2),
            "right": region.transpose(1, 0, 2)[::-1],
        }[side]
        n, length = lines.shape[:2]
        depth = max(2, round(params.band_depth * n))
        if n < 4 * (depth + 4) or length < 10:
            continue
        middle = lines[: depth + 4, length // 10 : length - length // 10]
        spread = np.linalg.norm(middle - np.median(middle, axis=1, keepdims=True), axis=2).mean(axis=1)
        # The band is the first run of lines [0, band) whose typical spread is low and after which
        # the spread jumps (the band's outer line may be blurred with the mount beyond it).
        band = 0
        for j in range(1, depth + 1):
            typical = float(np.median(spread[:j]))
            if typical < params.band_spread and spread[j : j + 3].mean() >= params.band_contrast * typical:
                band = j
                break
        if not band:
            continue
        cut = band + 2  # past the band and the blur of its edge
        cuts.append(side)
        if side == "top":
            y0 += cut
        elif side == "bottom":
            y1 -= cut
        elif side == "left":
            x0 += cut
        else:
            x1 -= cut
    return y0, x0, y1, x1, cuts


@dataclass
class _HalfArea:
    box: tuple[int, int, int, int]  # (x0, y0, x1, y1) working px, card-absolute
    area_fraction: float  # box area / half area
    photos: int  # large photo regions in the half
    notes: list[str]


def _half_area(mask: _Mask, x0: int, x1: int, params: PhotoAreaParams) -> _HalfArea | None:
    """Photo area inside working columns ``[x0, x1)``; None when the half has no photo cell."""
    bad = mask.non_photo[:, x0:x1]
    height, width = bad.shape
    # Cells of at least ``params.cell`` px, and few enough (<= 64 a side) for the pure-Python
    # histogram search to stay fast; the refinement then works in working px.
    cell = max(params.cell, int(np.ceil(max(height, width) / 64)))
    cell = min(cell, max(1, min(height, width) // 8))
    ch, cw = height // cell, width // cell
    if ch < 1 or cw < 1:
        return None
    pooled = bad[: ch * cell, : cw * cell].reshape(ch, cell, cw, cell).mean(axis=(1, 3))
    # A film edge or separator line may be thinner than a cell: it still separates.
    lined = np.asarray(mask.line_columns[x0 : x0 + cw * cell].reshape(cw, cell).any(axis=1))
    good = (pooled < 0.5) & ~lined[None, :]
    found = _largest_rectangle(good)
    if found is None:
        return None
    # The arch may be at the top or (a turned card) at the bottom: both are tried.
    rows = good.shape[0]
    from_top = _prefer_full_width(good, found, params.full_width_preference)
    turned = _prefer_full_width(good[::-1], (rows - found[2], found[1], rows - found[0], found[3]), params.full_width_preference)
    from_bottom = (rows - turned[2], turned[1], rows - turned[0], turned[3])
    wider = [r for r in (from_top, from_bottom) if r != found]
    r0, c0, r1, c1 = max(wider, key=lambda r: (r[2] - r[0]) * (r[3] - r[1])) if wider else found
    y0, bx0, y1, bx1 = _refine(bad, (r0 * cell, c0 * cell, r1 * cell, c1 * cell), params.clean_line, 2 * cell + 2)
    cuts: list[str] = []
    sides = {"top", "bottom", "left", "right"}
    for _ in range(params.edge_passes):
        # A further pass, on the sides just cut, finds a photo's edge behind a wide side title
        # or a caption band once those are cut off.
        y0, bx0, y1, bx1, found_cuts = _cut_straight_edges(
            mask.grey[:, x0:x1],
            mask.foreign[:, x0:x1],
            (y0, bx0, y1, bx1),
            params,
            sides,
        )
        cuts += [side for side in found_cuts if side not in cuts]
        sides = set(found_cuts)
        if not sides:
            break

    y0, bx0, y1, bx1, banded = _cut_uniform_bands(mask.lab[:, x0:x1], (y0, bx0, y1, bx1), params)

    # Two photos in one half (a three-photo card, a wrong split): two large separate regions,
    # or a plain strip running down the whole card through the box (a gutter the flood could
    # not reach; a pale wall in a picture does not go on through the mount above and below).
    count, _, stats, _ = cv2.connectedComponentsWithStats((~bad).astype(np.uint8), connectivity=4)
    photos = int(sum(stats[i, cv2.CC_STAT_AREA] >= 0.15 * bad.size for i in range(1, count)))
    margin = max(1, (bx1 - bx0) // 10)
    strip = mask.plain[:, x0 + bx0 + margin : x0 + bx1 - margin].mean(axis=0) >= 0.9
    if any(end - start >= 2 for start, end in _runs(strip)):
        photos = max(photos, 2)

    notes = [f"straight edge inside the {side} border (caption band, film edge or wedge)" for side in cuts]
    notes += [f"uniform band inside the {side} border (a frame or a strip)" for side in banded]
    above, below = bad[:y0, bx0:bx1], bad[y1:, bx0:bx1]
    # An arched top: above the box the photo region narrows (photo cells in the middle columns,
    # mount at the sides).
    if y0 >= 2:
        rows_above = slice(max(0, y0 - max(2, height // 12)), y0)
        band = ~bad[rows_above, bx0:bx1]
        third = max(1, (bx1 - bx0) // 6)
        corner = max(1, round(params.corner * (bx1 - bx0)))
        middle, sides = band[:, third:-third].mean(), np.concatenate((band[:, :third], band[:, -third:]), axis=1).mean()
        corners = np.concatenate((band[:, :corner], band[:, -corner:]), axis=1).mean()
        # Either the photo narrows above the box across its outer sixths, or only its very
        # corners are mount (a tall arch that meets the sides close to the box's corners).
        if middle > 0.5 and sides < middle - 0.25:
            notes.append(
                "arched top" if _plain_corners(band, mask.plain[rows_above, x0 + bx0 : x0 + bx1], third) else "uneven top edge"
            )
        elif middle > 0.9 and corners < middle - 0.1:
            notes.append("rounded top corners")
    for name, strip in (("above", above), ("below", below)):
        if strip.shape[0] == 0:
            continue
        rows = strip.mean(axis=1)
        dark_rows = mask.dark[:y0, x0 + bx0 : x0 + bx1] if name == "above" else mask.dark[y1:, x0 + bx0 : x0 + bx1]
        near = dark_rows[: max(1, height // 10)] if name == "below" else dark_rows[-max(1, height // 10) :]
        if near.size and near.mean(axis=1).max() > 0.6 and rows.max() > 0.6:
            notes.append(f"dark band {name} the photo (caption strip or film edge)")
    return _HalfArea(
        box=(x0 + bx0, y0, x0 + bx1, y1),
        area_fraction=(bx1 - bx0) * (y1 - y0) / float(height * width),
        photos=photos,
        notes=notes,
    )


def _clear_corners(bad: np.ndarray, box: Box, corner: float) -> Box:
    """Move the sides of ``box`` (``(x0, y0, x1, y1)``, ``bad``'s px) in until no non-photo
    pixel lies on a side's outer line within ``corner`` of the box's size from either end.
    Under an arch (or a rounded window) the largest rectangle's corners reach into the mount
    while its sides' middles are clean: the edge refinement's 1 % allowance hides a corner."""
    x0, y0, x1, y1 = box
    limit_x, limit_y = max(1, round(0.15 * (x1 - x0))), max(1, round(0.15 * (y1 - y0)))
    start = box
    for _ in range(max(limit_x, limit_y)):
        mx, my = max(2, round(corner * (x1 - x0))), max(2, round(corner * (y1 - y0)))
        moved = False
        if y0 - start[1] < limit_y and (bad[y0, x0 : x0 + mx].any() or bad[y0, x1 - mx : x1].any()):
            y0, moved = y0 + 1, True
        if start[3] - y1 < limit_y and (bad[y1 - 1, x0 : x0 + mx].any() or bad[y1 - 1, x1 - mx : x1].any()):
            y1, moved = y1 - 1, True
        if x0 - start[0] < limit_x and (bad[y0 : y0 + my, x0].any() or bad[y1 - my : y1, x0].any()):
            x0, moved = x0 + 1, True
        if start[2] - x1 < limit_x and (bad[y0 : y0 + my, x1 - 1].any() or bad[y1 - my : y1, x1 - 1].any()):
            x1, moved = x1 - 1, True
        if not moved or x1 - x0 < 4 or y1 - y0 < 4:
            break
    return x0, y0, x1, y1


def _clear_of_text(mask: _Mask, box: Box, x0: int, x1: int, params: PhotoAreaParams) -> Box:
    """Keep ``box`` (``(x0, y0, x1, y1)``, working px) ``text_clearance`` of the card's width
    away from printed text beside or across its sides (a collection stamp by the photo can run
    onto the photo's plain margin, which the mount's flood does not reach).

    Ink: strokes much darker or lighter than their surroundings (morphological black-hat and
    top-hat over a stroke-sized window), letters merged into words by a closing of the same
    size. Text: a word no taller or wider than a few letters whose surroundings are mostly plain
    or non-photo (mount, a printed margin), not a photo's texture. A word that reaches outside
    a side, overlapping the box's span along it, pushes that side past it. Only columns
    ``[x0, x1)`` (the half) are looked at."""
    if params.text_clearance <= 0:
        return box
    height, width = mask.grey.shape
    clearance = max(1, round(params.text_clearance * width))
    bx0, by0, bx1, by1 = box
    lo_y, hi_y = max(0, by0 - 4 * clearance), min(height, by1 + 4 * clearance)
    lo_x, hi_x = max(x0, bx0 - 4 * clearance), min(x1, bx1 + 4 * clearance)
    grey = mask.grey[lo_y:hi_y, lo_x:hi_x]
    size = max(3, round(0.015 * width)) | 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    ink = (cv2.morphologyEx(grey, cv2.MORPH_BLACKHAT, kernel) > params.ink_contrast) | (
        cv2.morphologyEx(grey, cv2.MORPH_TOPHAT, kernel) > params.ink_contrast
    )
    words = cv2.morphologyEx(ink.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((size, size), np.uint8))
    count, _, stats, _ = cv2.connectedComponentsWithStats(words, connectivity=8)
    plain = mask.foreign[lo_y:hi_y, lo_x:hi_x]
    h, w = grey.shape
    for i in range(1, count):
        cx, cy, cw, ch, _area = (int(v) for v in stats[i])
        if min(cw, ch) > 4 * size:  # a word (or a stamp of a few lines) is thin across its lines
            continue
        ring = (slice(max(0, cy - 2), min(h, cy + ch + 2)), slice(max(0, cx - 2), min(w, cx + cw + 2)))
        background = ~ink[ring]
        if background.sum() == 0 or plain[ring][background].mean() < params.text_background:
            continue
        gx0, gy0, gx1, gy1 = cx + lo_x, cy + lo_y, cx + cw + lo_x, cy + ch + lo_y
        if gy1 > by0 and gy0 < by1:  # beside the left or right side
            if gx0 < bx0 < gx1 + clearance and gx1 < (bx0 + bx1) // 2:
                bx0 = max(bx0, gx1 + clearance)
            if gx0 - clearance < bx1 < gx1 and gx0 > (bx0 + bx1) // 2:
                bx1 = min(bx1, gx0 - clearance)
        if gx1 > bx0 and gx0 < bx1:  # above or below
            if gy0 < by0 < gy1 + clearance and gy1 < (by0 + by1) // 2:
                by0 = max(by0, gy1 + clearance)
            if gy0 - clearance < by1 < gy1 and gy0 > (by0 + by1) // 2:
                by1 = min(by1, gy0 - clearance)
    if bx1 - bx0 < 0.8 * (box[2] - box[0]) or by1 - by0 < 0.8 * (box[3] - box[1]):
        return box  # text all round a box is a mistaken reading, not a reason to cut the photo down
    return bx0, by0, bx1, by1


def _turned(mask: _Mask) -> _Mask:
    """``mask`` turned by 180 degrees (a view: no copy)."""
    return _Mask(
        scale_x=mask.scale_x,
        scale_y=mask.scale_y,
        grey=mask.grey[::-1, ::-1],
        non_photo=mask.non_photo[::-1, ::-1],
        foreign=mask.foreign[::-1, ::-1],
        line_columns=mask.line_columns[::-1],
        plain=mask.plain[::-1, ::-1],
        mount=mask.mount[::-1, ::-1],
        dark=mask.dark[::-1, ::-1],
        white=mask.white[::-1, ::-1],
        mount_rgb=mask.mount_rgb,
        lab=mask.lab[::-1, ::-1],
    )


def _plain_corners(band: np.ndarray, plain: np.ndarray, side: int) -> bool:
    """Whether what is not photo in the outer ``side`` columns of ``band`` (bool, True = photo:
    the rows just above a box) is plain, as a mount is: under a real arch the corners are bare
    card. Dark foliage or a pale sky taken for mount also make the photo narrow above a box, but
    are textured (measured: the rounded-rectangle window of a black mount with dark trees at its
    foot read as an arched bottom on two of three scales of one card)."""
    shares = []
    for columns in (slice(0, side), slice(band.shape[1] - side, band.shape[1])):
        outer = ~band[:, columns]
        if outer.any():
            shares.append(float(plain[:, columns][outer].mean()))
    return bool(shares) and max(shares) >= 0.8


def _curved_top(note: str) -> bool:
    return note in ("arched top", "rounded top corners", "uneven top edge")


def _half_area_both_ways(mask: _Mask, turned: _Mask, x0: int, x1: int, params: PhotoAreaParams) -> _HalfArea | None:
    """The photo area of working columns ``[x0, x1)``, found on the card as it is and turned by
    180 degrees, intersected. The search is not symmetric (the cell grid starts at the top left,
    an arch is looked for at the top, ties between equal rectangles go to the first found), so
    its mistakes differ between the two; what both agree is photo is kept. The result is then the
    same for a card and its turned copy."""
    upright = _half_area(mask, x0, x1, params)
    height, width = mask.non_photo.shape
    flipped = _half_area(turned, width - x1, width - x0, params)
    if upright is None or flipped is None:
        return None
    fx0, fy0, fx1, fy1 = flipped.box
    back = (width - fx1, height - fy1, width - fx0, height - fy0)
    box = (max(upright.box[0], back[0]), max(upright.box[1], back[1]), min(upright.box[2], back[2]), min(upright.box[3], back[3]))
    # Under an arch the box's corner meets the curve inside the photo's sides, where the curve
    # is nearly vertical: the arch meets the sides lower. An extra inset covers that (before the
    # corners are checked: the drop usually clears them, which keeps the sides).
    arch_drop = round(params.arch_inset * (box[3] - box[1]))
    if any(_curved_top(note) for note in upright.notes):
        box = (box[0], box[1] + arch_drop, box[2], box[3])
    if any(_curved_top(note) for note in flipped.notes):
        box = (box[0], box[1], box[2], box[3] - arch_drop)
    box = _clear_corners(mask.non_photo, box, params.corner)
    box = _clear_of_text(mask, box, x0, x1, params)
    if box[2] - box[0] < 2 or box[3] - box[1] < 2:
        return None
    turned_notes = {"top": "bottom", "bottom": "top", "left": "right", "right": "left", "above": "below", "below": "above"}
    notes = list(upright.notes)
    for note in flipped.notes:
        words = [turned_notes.get(word, word) for word in note.split(" ")]
        if " ".join(words) not in notes:
            notes.append(" ".join(words))
    return _HalfArea(
        box=box,
        area_fraction=(box[2] - box[0]) * (box[3] - box[1]) / float(height * (x1 - x0)),
        photos=max(upright.photos, flipped.photos),
        notes=notes,
    )


# ------------------------------------------------------------------------------------- API


def _fallback(split: CardSplit, reason: str, evidence: list[str], params: PhotoAreaParams) -> PhotoAreas:
    return PhotoAreas(
        left_box=split.left_box,
        right_box=split.right_box,
        gutter_x=split.gutter_x,
        confidence=round(min(params.fallback_confidence, split.confidence), 4),
        evidence=tuple(evidence),
        fallback_reason=reason,
        split=split,
    )


def find_photo_areas(card: np.ndarray, params: PhotoAreaParams = PhotoAreaParams()) -> PhotoAreas:
    """The largest artifact-free rectangle of photograph in each half of a stereo card.

    ``card``: ``uint8`` or ``uint16``, ``(H, W)`` or ``(H, W, 3)``, at least 32 x 16 px, else
    :class:`InvalidInputError`. The card is split with :func:`pipeline.split.split_card`
    (``params.split``); each box lies inside its half of that split. Never raises for a valid
    card: when the photo areas are not trustworthy the split's boxes come back with
    ``fallback_reason`` set and a low confidence. See the module docstring.
    """
    card = as_card(card)
    split = split_card(card, params.split)
    height, width = card.shape[:2]
    if split.method == "centre":
        return _fallback(split, "no stereo pair or gutter found: the card was cut at its middle", [], params)

    mask = _measure(card, params)
    turned = _turned(mask)
    gutter = int(np.clip(round(split.gutter_x / mask.scale_x), 1, mask.non_photo.shape[1] - 1))
    evidence: list[str] = []
    if mask.mount_rgb is not None:
        evidence.append(f"mount of colour RGB{mask.mount_rgb} around the photos")
    else:
        evidence.append("no mount colour around the card")
    if mask.dark.mean() > 0.01:
        evidence.append("dark plain strips (film edges, black mount or scan background)")
    if mask.white.mean() > 0.01:
        evidence.append("white plain margins")
    text = mask.non_photo & ~(mask.mount | mask.dark | mask.white)
    if mask.mount_rgb is not None and text.mean() > 0.005:
        evidence.append("printed text on the mount")

    left_half = _half_area_both_ways(mask, turned, 0, gutter, params)
    right_half = _half_area_both_ways(mask, turned, gutter, mask.non_photo.shape[1], params)
    if left_half is None or right_half is None:
        return _fallback(split, "no photo found in a half (blank or plain card)", evidence, params)
    halves = [left_half, right_half]
    for name, half in zip(("left", "right"), halves):
        evidence.extend(f"{name}: {note}" for note in half.notes)
    if not (mask.non_photo.any()):
        return _fallback(split, "no border found: the photos fill their halves", evidence, params)
    small = [name for name, half in zip(("left", "right"), halves) if half.area_fraction < params.min_area]
    if small:
        return _fallback(
            split, f"photo area of the {' and '.join(small)} half below {params.min_area:.0%} of it", evidence, params
        )
    several = [name for name, half in zip(("left", "right"), halves) if half.photos > 1]
    if several:
        return _fallback(split, f"more than one photo in the {' and '.join(several)} half", evidence, params)

    boxes = []
    for half, (lo, hi) in zip(halves, ((0, split.gutter_x), (split.gutter_x, width))):
        x0, y0, x1, y1 = half.box
        boxes.append(
            (
                int(np.clip(np.ceil(x0 * mask.scale_x), lo, hi - 1)),
                int(np.clip(np.ceil(y0 * mask.scale_y), 0, height - 1)),
                int(np.clip(np.floor(x1 * mask.scale_x), lo + 1, hi)),
                int(np.clip(np.floor(y1 * mask.scale_y), 1, height)),
            )
        )
    widths = [b[2] - b[0] for b in boxes]
    heights = [b[3] - b[1] for b in boxes]
    agreement = min(min(widths) / max(widths), min(heights) / max(heights))
    if agreement < params.min_agreement:
        return _fallback(
            split,
            f"the halves' photo areas differ too much ({widths[0]}x{heights[0]} vs {widths[1]}x{heights[1]} px)",
            evidence,
            params,
        )
    # Same rows for both crops: the intersection of the two row ranges lies inside both photo
    # areas (photos of a pair are mounted level, up to a few px). Widths stay as found: disparity
    # makes them differ, and the crop stage cuts both to their aligned intersection anyway.
    top, bottom = max(boxes[0][1], boxes[1][1]), min(boxes[0][3], boxes[1][3])
    if bottom - top < params.min_agreement * max(heights):
        return _fallback(split, f"the halves' photo areas share too few rows ({top}..{bottom})", evidence, params)
    pad = round(params.inset * width)
    left_box, right_box = (
        (x0 + pad, top + pad, max(x0 + pad + 1, x1 - pad), max(top + pad + 1, bottom - pad)) for x0, _, x1, _ in boxes
    )
    coverage = min(1.0, min(h.area_fraction for h in halves) / 0.5)
    confidence = round(float(np.clip(agreement * coverage * (0.5 + 0.5 * split.confidence), 0.0, 1.0)), 4)
    return PhotoAreas(
        left_box=left_box,
        right_box=right_box,
        gutter_x=split.gutter_x,
        confidence=confidence,
        evidence=tuple(evidence),
        fallback_reason=None,
        split=split,
    )


# ---------------------------------------------------------------------- crop proposals


def _photo_line(mask: _Mask, axis: int, line: int, step: int, span: slice, photo_share: float, params: PhotoAreaParams) -> bool:
    """Whether working-scale row (``axis`` 0) or column (1) ``line``, reached by moving ``step``
    (-1 or +1) out of a photo, is still photo along ``span``: at least ``photo_share`` of it is
    not in the non-photo mask, and between the line before it and the one after it most pixels
    do not change the same way (a print's straight edge, as ``straight_edge`` measures one)."""
    if np.mean(~np.take(mask.non_photo, line, axis=axis)[span]) < photo_share:
        return False
    size = mask.grey.shape[axis]
    inner = np.take(mask.grey, line - step, axis=axis)[span]
    beyond = np.take(mask.grey, min(size - 1, max(0, line + step)), axis=axis)[span]
    change = beyond - inner
    share = max(float(np.mean(change > params.edge_step)), float(np.mean(change < -params.edge_step)))
    return share < params.straight_edge


def _grow_side(mask: _Mask, axis: int, start: int, limit: int, span: slice, photo_share: float, params: PhotoAreaParams) -> int:
    """From line ``start``, move one line at a time towards ``limit`` (inclusive) while the next
    line is photo (:func:`_photo_line`); returns where the side stops."""
    step = -1 if limit < start else 1
    position = start
    while position != limit and _photo_line(mask, axis, position + step, step, span, photo_share, params):
        position += step
    return position


def grow_to_photo_edges(
    card: np.ndarray,
    boxes: Sequence[Box],
    params: PhotoAreaParams = PhotoAreaParams(),
    *,
    reach: float = 0.35,
    core: float = 0.8,
    photo_share: float = 0.5,
    pad: float = 0.004,
) -> tuple[Box, ...]:
    """Each of ``boxes`` grown outwards to the edges of the photo it lies in: what a crop task
    starts from, so that annotators trim a box rather than pull each side out to the photo.

    :func:`find_photo_areas` is safe by design (every box strictly inside the photo, arches,
    bands and stamps cut off, inset by ``params.inset``): on the demo cards its boxes cover
    50-80 % of the prints. Here each side moves out, one working-scale line at a time, while the
    next line is photo on at least ``photo_share`` of its middle ``core`` fraction (the middle,
    so an arched top or a rounded corner does not stop the side early), by at most ``reach`` of
    the box's size; the non-photo mask is the one :func:`find_photo_areas` uses (mount colour,
    dark and white plain strips flooded from the card's frame, printed text closed over). Then
    each side is pulled in by ``pad`` of the card's width (a print's edge is blurred).

    ``card`` as :func:`find_photo_areas` takes it; ``boxes`` ``(x0, y0, x1, y1)`` in card pixels,
    exclusive ends. A grown box never becomes smaller than the box it started from, and a box
    with no room in the working copy comes back as it was.
    """
    card = as_card(card)
    height, width = card.shape[:2]
    mask = _measure(card, params)
    rows, columns = mask.non_photo.shape
    inset = round(pad * width)
    # A box grows up to the middle of the gap to its neighbour, never into the other photo.
    order = sorted(range(len(boxes)), key=lambda i: boxes[i][0])
    left_limit = [0.0] * len(boxes)
    right_limit = [float(width)] * len(boxes)
    for a, b in zip(order, order[1:]):
        middle = (boxes[a][2] + boxes[b][0]) / 2
        right_limit[a], left_limit[b] = middle, middle
    grown: list[Box] = []
    for index, box in enumerate(boxes):
        x0, y0, x1, y1 = (int(v) for v in box)
        # Working px, rounded inwards: the start is photo wherever the box was.
        bx0, by0 = int(np.ceil(x0 / mask.scale_x)), int(np.ceil(y0 / mask.scale_y))
        bx1, by1 = int(np.floor(x1 / mask.scale_x)) - 1, int(np.floor(y1 / mask.scale_y)) - 1  # inclusive
        if not (0 <= bx0 < bx1 < columns and 0 <= by0 < by1 < rows):
            grown.append((x0, y0, x1, y1))
            continue
        reach_x, reach_y = round(reach * (bx1 - bx0 + 1)), round(reach * (by1 - by0 + 1))
        for _ in range(2):  # the sides meet at the corners: the second pass sees the others' new extent
            cx, cw = bx0 + (1 - core) / 2 * (bx1 - bx0), core * (bx1 - bx0)
            cy, ch = by0 + (1 - core) / 2 * (by1 - by0), core * (by1 - by0)
            middle_columns = slice(int(cx), max(int(cx) + 1, int(cx + cw)))
            middle_rows = slice(int(cy), max(int(cy) + 1, int(cy + ch)))
            by0 = _grow_side(mask, 0, by0, max(0, by0 - reach_y), middle_columns, photo_share, params)
            by1 = _grow_side(mask, 0, by1, min(rows - 1, by1 + reach_y), middle_columns, photo_share, params)
            low = max(0, bx0 - reach_x, int(np.ceil(left_limit[index] / mask.scale_x)))
            high = min(columns - 1, bx1 + reach_x, int(np.floor(right_limit[index] / mask.scale_x)) - 1)
            bx0 = _grow_side(mask, 1, bx0, min(bx0, low), middle_rows, photo_share, params)
            bx1 = _grow_side(mask, 1, bx1, max(bx1, high), middle_rows, photo_share, params)
        out = (
            int(np.ceil(bx0 * mask.scale_x)) + inset,
            int(np.ceil(by0 * mask.scale_y)) + inset,
            int(np.floor((bx1 + 1) * mask.scale_x)) - inset,
            int(np.floor((by1 + 1) * mask.scale_y)) - inset,
        )
        # Never smaller than the start, never outside the card.
        grown.append(
            (
                max(0, min(out[0], x0)),
                max(0, min(out[1], y0)),
                min(width, max(out[2], x1)),
                min(height, max(out[3], y1)),
            )
        )
    return tuple(grown)
