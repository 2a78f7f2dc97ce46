"""Crop alignment (KeystoneDepth's crop step, Luo et al.): SIFT matches inside the two crop boxes align them, then both are
cut to their intersection so that the two crops have the same size.

Conventions
-----------
- Boxes are ``(x0, y0, x1, y1)`` in card pixels, ``x1``/``y1`` exclusive (as in :mod:`pipeline.split`).
- Matches are taken in *box-relative* coordinates (origin at each box's top-left pixel).
  The recovered translation ``(dx, dy)`` says: a **far** scene point at ``(x, y)`` in the left
  crop appears at ``(x + dx, y + dy)`` in the right crop.

  * ``dy``: the median vertical offset of the consensus matches (a stereo pair has one row offset).
  * ``dx``: the horizontal offset of the *far* content, the ``far_percentile`` [95] percentile of the
    horizontal offsets (``x_r - x_l``; far content has the smallest disparity ``x_l - x_r``, i.e.
    the largest offset). After alignment the far content lines up (disparity ~0) and ~95 % of the
    matches have disparity ``>= 0``, the paper's "no negative disparity" rule. ``far_percentile=50``
    gives the median offset instead (the middle of the scene lines up).
- ``dx``/``dy`` are rounded to whole pixels for the boxes (crops stay pixel-exact, no resampling);
  the unrounded values are recorded.

Consensus: matches whose vertical offset lies within ``row_tolerance`` px of the median, and whose
horizontal offset lies within ``disparity_fence`` robust sigmas (1.4826 MAD, at least 1 % of the
crop width) of the median (along-row mismatches out). Errors: :class:`InvalidInputError` for boxes
outside the card, inverted or smaller than 16 px; :class:`TooFewCropMatchesError` for fewer than
``min_matches`` consensus matches; :class:`EmptyIntersectionError` when the aligned boxes overlap
by less than 16 px in a dimension.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .contracts import check_image
from .errors import InvalidInputError, PipelineError
from .rectify import RectifyParams, match_features

__all__ = [
    "CropAlignParams",
    "CropAlignment",
    "CropAlignmentError",
    "EmptyIntersectionError",
    "TooFewCropMatchesError",
    "align_crops",
    "matches_in_boxes",
]

Box = tuple[int, int, int, int]
MIN_SIDE = 16  # px: a smaller box (before or after alignment) is refused


class CropAlignmentError(PipelineError):
    """The two crop boxes could not be aligned; ``code`` says why."""

    code = "crop_alignment_failed"


class TooFewCropMatchesError(CropAlignmentError):
    code = "too_few_matches"


class EmptyIntersectionError(CropAlignmentError):
    code = "empty_intersection"


@dataclass(frozen=True)
class CropAlignParams:
    ratio: float = 0.7
    """Lowe ratio test (the paper's value)."""
    max_side: int = 1200
    """px: crops are downscaled to this longer side for SIFT only."""
    max_keypoints: int = 4000
    min_matches: int = 10
    """Fewer consensus matches: :class:`TooFewCropMatchesError`."""
    row_tolerance: float = 3.0
    """px: a match is in the consensus when its vertical offset is within this of the median."""
    disparity_fence: float = 5.0
    """Robust sigmas around the median horizontal offset (along-row mismatches are left out)."""
    far_percentile: float = 95.0
    """Percentile of the horizontal offsets taken as the far content's offset (50 = median)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.ratio <= 1.0:
            raise InvalidInputError(f"Expected 0 < ratio <= 1, got {self.ratio}")
        if self.min_matches < 1 or self.row_tolerance <= 0 or self.disparity_fence <= 0:
            raise InvalidInputError("Expected min_matches >= 1, row_tolerance > 0 and disparity_fence > 0")
        if not 0.0 <= self.far_percentile <= 100.0:
            raise InvalidInputError(f"Expected 0 <= far_percentile <= 100, got {self.far_percentile}")


@dataclass(frozen=True)
class CropAlignment:
    """Boxes before and after alignment (card px, x1/y1 exclusive) and the translation found."""

    left_box_before: Box
    right_box_before: Box
    left_box: Box
    right_box: Box
    dx: float  # px: far content at left-crop (x, y) is at right-crop (x + dx, y + dy) (boxes before)
    dy: float
    dy_spread: float  # px: median |vertical offset - dy| over the consensus (rotation / noise)
    matches: int  # ratio-test matches between the two boxes
    inliers: int  # matches in the translation consensus
    seconds: float = 0.0
    points: tuple[np.ndarray, np.ndarray] = field(default=(np.zeros((0, 2)), np.zeros((0, 2))), repr=False)
    """Every ratio-test match ``(pts_l, pts_r)``, ``(N, 2)`` px relative to the boxes *before*
    alignment (full resolution, origin at the box's top-left pixel centre)."""

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) px of both aligned crops."""
        return self.left_box[2] - self.left_box[0], self.left_box[3] - self.left_box[1]

    def matches_in_crops(self) -> tuple[np.ndarray, np.ndarray]:
        """The matches as ``(pts_l, pts_r)`` in px of the aligned crops (``left_box`` /
        ``right_box``), only those inside both: rectification can reuse the SIFT work done here
        instead of matching the same crops again."""
        pts_l, pts_r = self.points
        width, height = self.size
        pts_l = pts_l - np.array([self.left_box[0] - self.left_box_before[0], self.left_box[1] - self.left_box_before[1]])
        pts_r = pts_r - np.array([self.right_box[0] - self.right_box_before[0], self.right_box[1] - self.right_box_before[1]])
        inside = np.ones(len(pts_l), bool)
        for pts in (pts_l, pts_r):
            inside &= (pts[:, 0] >= -0.5) & (pts[:, 0] < width - 0.5) & (pts[:, 1] >= -0.5) & (pts[:, 1] < height - 0.5)
        return pts_l[inside], pts_r[inside]

    def metrics(self) -> dict[str, Any]:
        return {
            "left_box_before": list(self.left_box_before),
            "right_box_before": list(self.right_box_before),
            "left_box": list(self.left_box),
            "right_box": list(self.right_box),
            "dx": round(float(self.dx), 3),
            "dy": round(float(self.dy), 3),
            "dy_spread": round(float(self.dy_spread), 3),
            "matches": int(self.matches),
            "inliers": int(self.inliers),
            "size": list(self.size),
            "convention": "far content at left-crop (x, y) is at right-crop (x + dx, y + dy)",
            "seconds": round(float(self.seconds), 4),
        }


def matches_in_boxes(card_matches: np.ndarray, left_box: Box, right_box: Box) -> tuple[np.ndarray, np.ndarray]:
    """Matches ``(N, 4)`` ``[x_a, y_a, x_b, y_b]`` in card px (e.g. the filter's, between its two
    halves) as ``(pts_l, pts_r)`` relative to ``left_box`` / ``right_box``: a match counts when one
    end lies in each box, whichever end is in which (boxes exchanged by a swap still find them)."""
    m = np.asarray(card_matches, np.float64).reshape(-1, 4)
    a, b = m[:, :2], m[:, 2:]

    def inside(pts: np.ndarray, box: Box) -> np.ndarray:
        return (pts[:, 0] >= box[0] - 0.5) & (pts[:, 0] < box[2] - 0.5) & (pts[:, 1] >= box[1] - 0.5) & (pts[:, 1] < box[3] - 0.5)

    forward = inside(a, left_box) & inside(b, right_box)
    backward = inside(b, left_box) & inside(a, right_box) & ~forward
    pts_l = np.vstack([a[forward], b[backward]]) - np.array(left_box[:2], np.float64)
    pts_r = np.vstack([b[forward], a[backward]]) - np.array(right_box[:2], np.float64)
    return pts_l, pts_r


def _check_box(box: object, name: str, width: int, height: int) -> Box:
    expected = f"Expected {name} as four numbers (x0, y0, x1, y1), got {box!r}"
    if not isinstance(box, Iterable):
        raise InvalidInputError(expected)
    try:
        values = [float(v) for v in box]
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(expected) from exc
    if len(values) != 4 or not all(np.isfinite(values)) or any(v != round(v) for v in values):
        raise InvalidInputError(f"Expected {name} as four whole numbers (x0, y0, x1, y1), got {box!r}")
    x0, y0, x1, y1 = (int(v) for v in values)
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        raise InvalidInputError(f"Expected {name} inside the {width}x{height} card with x0 < x1, y0 < y1, got {box!r}")
    if x1 - x0 < MIN_SIDE or y1 - y0 < MIN_SIDE:
        raise InvalidInputError(f"Expected {name} of at least {MIN_SIDE}x{MIN_SIDE} px, got {box!r}")
    return x0, y0, x1, y1


def align_crops(
    card: np.ndarray,
    left_box: Box,
    right_box: Box,
    params: CropAlignParams = CropAlignParams(),
    matches: tuple[np.ndarray, np.ndarray] | None = None,
) -> CropAlignment:
    """Align two crop boxes on ``card`` (uint8 ``(H, W)``/``(H, W, 3)``) by a SIFT translation and
    cut both to their intersection in aligned coordinates (conventions in the module docstring).
    ``matches``: SIFT matches already found (``(pts_l, pts_r)``, ``(N, 2)`` px relative to the
    boxes, e.g. the filter's, :func:`matches_in_boxes`); None: match the boxes here.

    The returned ``left_box`` / ``right_box`` lie inside the card, inside the boxes given, and
    have the same size; ``card[right_box]`` row ``r`` shows the same scene row as ``card[left_box]``
    row ``r`` (to the rounding of ``dy``), and far content is in the same column.
    """
    clock = time.perf_counter()
    check_image(card, "the card", MIN_SIDE, MIN_SIDE)
    height, width = card.shape[:2]
    lb = _check_box(left_box, "left_box", width, height)
    rb = _check_box(right_box, "right_box", width, height)
    left = np.ascontiguousarray(card[lb[1] : lb[3], lb[0] : lb[2]])
    right = np.ascontiguousarray(card[rb[1] : rb[3], rb[0] : rb[2]])
    if matches is None:
        rp = RectifyParams(ratio=params.ratio, max_side=params.max_side, max_keypoints=params.max_keypoints)
        pts_l, pts_r = match_features(left, right, rp)
    else:
        pts_l, pts_r = (np.asarray(p, np.float64).reshape(-1, 2) for p in matches)
        if pts_l.shape != pts_r.shape or not (np.all(np.isfinite(pts_l)) and np.all(np.isfinite(pts_r))):
            raise InvalidInputError(f"Expected two finite (N, 2) match arrays, got {pts_l.shape} and {pts_r.shape}")
    n = len(pts_l)
    if n < params.min_matches:
        raise TooFewCropMatchesError(f"{n} SIFT matches between the boxes < {params.min_matches}")
    off = pts_r - pts_l
    keep = np.abs(off[:, 1] - np.median(off[:, 1])) <= params.row_tolerance
    if keep.sum() >= params.min_matches:  # refine the row consensus once around its own median
        keep = np.abs(off[:, 1] - np.median(off[keep, 1])) <= params.row_tolerance
    ox = off[keep, 0]
    if len(ox):
        med = float(np.median(ox))
        sigma = max(1.4826 * float(np.median(np.abs(ox - med))), 0.01 * min(left.shape[1], right.shape[1]))
        keep[keep] = np.abs(ox - med) <= params.disparity_fence * sigma
    n_in = int(keep.sum())
    if n_in < params.min_matches:
        raise TooFewCropMatchesError(f"{n_in} matches agree on one translation (of {n}) < {params.min_matches}")
    dy = float(np.median(off[keep, 1]))
    dx = float(np.percentile(off[keep, 0], params.far_percentile))
    spread = float(np.median(np.abs(off[keep, 1] - dy)))

    ix, iy = round(dx), round(dy)
    # Left-crop coordinates covered by both: [0, wL) and [-ix, wR - ix) (same in y).
    wl, hl = lb[2] - lb[0], lb[3] - lb[1]
    wr, hr = rb[2] - rb[0], rb[3] - rb[1]
    x0, x1 = max(0, -ix), min(wl, wr - ix)
    y0, y1 = max(0, -iy), min(hl, hr - iy)
    if x1 - x0 < MIN_SIDE or y1 - y0 < MIN_SIDE:
        raise EmptyIntersectionError(
            f"aligned boxes overlap by {max(0, x1 - x0)}x{max(0, y1 - y0)} px (offset {dx:.1f}, {dy:.1f})"
        )
    new_l = (lb[0] + x0, lb[1] + y0, lb[0] + x1, lb[1] + y1)
    new_r = (rb[0] + x0 + ix, rb[1] + y0 + iy, rb[0] + x1 + ix, rb[1] + y1 + iy)
    return CropAlignment(
        left_box_before=lb,
        right_box_before=rb,
        left_box=new_l,
        right_box=new_r,
        dx=dx,
        dy=dy,
        dy_spread=spread,
        matches=n,
        inliers=n_in,
        seconds=time.perf_counter() - clock,
        points=(pts_l, pts_r),
    )
