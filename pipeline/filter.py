"""The paper's stereo filter: SIFT good-match fraction between the two halves of a card.

KeystoneDepth culls scans that are not stereo pairs by matching SIFT features between the
halves with Lowe's ratio test [0.7] and routing on the fraction of good matches:

``good_match_fraction = good_matches / keypoints_left``

The denominator is the number of SIFT keypoints in the **left** half: every left keypoint is a
query that either finds a good match in the right half or not, so the fraction lies in [0, 1]
and reads as "share of the left photo's features seen again in the right photo". It is recorded
with every result (``FilterResult.denominator``) and must not change without a new parameter
hash, since the thresholds are calibrated on it.

Routing (pure, see :func:`route`): fewer than ``min_good_matches`` [10] good matches, or a
fraction below ``cull_fraction`` [0.5 %], is *culled*; a fraction in ``[cull_fraction,
review_fraction)`` [0.5 %, 1.5 %) goes to human *review*; anything higher *passes*. Measured on
these machines: true pairs 20-34 %, unrelated images 0.25-0.45 %, an image against its own
mirror 1.7 %.

Stereo geometry check (on by default, ``check_geometry``): the paper counts every ratio-test
match, but letters repeated on a card back, or an image against its mirror, also give matches
(measured here: a card back 36 matches, 8.9 %; a mirrored photo 2.3 %: both would pass). Matches
of a real pair agree with one stereo geometry: in coordinates relative to each half, the same
vertical offset (within ``row_tolerance`` of the median) and a horizontal offset within the
disparity range (``disparity_tolerance`` of the median), with the median offsets themselves
plausible (the boxes frame the same scene). Real pairs measured here: 85-100 % of good matches
agree; card backs and mirrors 0-31 %. Fewer than ``min_good_matches`` agreeing matches culls
the card; fewer than ``min_consistent_share`` of them sends a passing card to review. The
fraction itself stays the paper's (all good matches / left keypoints).

Determinism: SIFT has no random state, and matching is exhaustive (the exact two nearest
neighbours by L2 distance, what ``cv2.BFMatcher`` with ``NORM_L2`` gives; see
:func:`ratio_test_matches`), not FLANN's randomised trees, so a card always gets the same numbers.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from .contracts import check_image
from .contrast import stretch_contrast
from .errors import InvalidInputError
from .split import CardSplit, SplitParams, crop_halves, split_card

Outcome = Literal["pass", "review", "culled"]

DENOMINATOR = "keypoints_left"


@dataclass(frozen=True)
class FilterParams:
    """Parameters of the SIFT filter (thresholds are fractions, not percent)."""

    ratio: float = 0.7
    """Lowe ratio test: a match is good if its distance < ratio x the second-best distance."""
    cull_fraction: float = 0.005
    """Good-match fraction below this: culled."""
    review_fraction: float = 0.015
    """Fraction in [cull_fraction, review_fraction): human review; at or above: pass."""
    min_good_matches: int = 10
    """Fewer good matches than this: culled, whatever the fraction."""
    max_side: int = 600
    """px: each half is resampled (area filter down, bicubic up) so its longer side is this. SIFT time
    grows with pixels (a 3000 px scan half would take seconds); at ~600 px the halves are at
    the scale of the paper's web-size scans, where the thresholds above were measured, and
    fine film grain and JPEG noise no longer make keypoints. The good matches found here are
    reused by crop alignment and rectification (the rectify stage): this is the card's one SIFT
    pass. Measured 2026-11-24: 480 px / 1,500 keypoints would save 0.12-0.15 s on 1400-3000 px
    scans, but an unrelated pair's fraction rises from under 0.5 % to 0.69 % (the thresholds'
    calibration moves) and the 3000 px sports pair's rectification moves 1.6 deg under a 16 px
    crop (``benchmarks.rectify_real``), so the side stays 600."""
    max_keypoints: int = 2000
    """SIFT keeps at most this many keypoints per half, the strongest (0: all, as the paper).
    Grainy raw scans give 5,000+ keypoints per 600 px half and brute-force matching grows with
    the product of the counts (``cv2.BFMatcher``: 0.56 s for 5,620 x 5,474 on one core, 0.08 s for
    2,000 x 2,000; :func:`ratio_test_matches`, the same pairs, 0.02 s for 2,000 x 2,000); the cap
    bounds a card at about 0.3 s. It also bounds the denominator: fractions of capped
    true pairs read a few points higher (measured 24-32 % -> 33-38 %), unrelated pairs do not
    change (0.2-0.6 %). Measured 2026-11-24, 2,000 -> 1,500 (not taken): the NYPL cards and card
    backs (at most 1,491 keypoints a half) give identical results and the 1400-3000 px scans
    0.05-0.10 CPU-s less, but rectification from the fewer matches moves: a synthetic 3,850 px
    card's measured disparity maximum 63.5 -> 52 px (the disparity search is set from it), the
    sports JPS pair's change under a 16 px crop 0.41 -> 0.90 deg (``benchmarks.rectify_real``)."""
    reduced_decode: bool = True
    """The filter stage decodes a JPEG scan at 1/2, 1/4 or 1/8 of its size (libjpeg's scaled
    decode, :func:`pipeline.io.read_image_reduced`) when the card stays at least
    :func:`decode_width` px wide: the split analyses an ``analysis_width`` copy and SIFT a
    ``max_side`` one, so nothing it measures needs more. Boxes and matches are given in the full
    card's pixels either way. Measured 2026-11-24 on the three ~3000 px JPS scans (decoded at
    1/2), the filter stage's CPU-s a card, best of three: 0.42 -> 0.36, 0.48 -> 0.41, 0.42 -> 0.36
    (a cheaper decode, and a 4x smaller card to split, cut and shrink); cards under 2,700 px wide
    are decoded as before (the 1400 px raw scans: 0.37 and 0.31 either way)."""
    check_geometry: bool = True
    """Require good matches to agree with one stereo geometry (see the module docstring)."""
    row_tolerance: float = 0.03
    """Fraction of the half's height: largest vertical offset from the median of a good match."""
    disparity_tolerance: float = 0.1
    """Fraction of the half's width: largest horizontal offset from the median of a good match."""
    min_consistent_share: float = 0.5
    """A passing card whose agreeing share of good matches is below this goes to review."""
    split: SplitParams = field(default_factory=SplitParams)
    """How the card is split into halves (:func:`pipeline.split.split_card`)."""

    def __post_init__(self) -> None:
        # Wiring errors surface when parameters are built, not halfway through a run.
        if not 0.0 < self.ratio <= 1.0:
            raise InvalidInputError(f"Expected 0 < ratio <= 1, got {self.ratio}")
        if not 0.0 <= self.cull_fraction <= self.review_fraction <= 1.0:
            raise InvalidInputError(
                f"Expected 0 <= cull_fraction <= review_fraction <= 1, got {self.cull_fraction}, {self.review_fraction}"
            )
        if self.min_good_matches < 0:
            raise InvalidInputError(f"Expected min_good_matches >= 0, got {self.min_good_matches}")
        if not (0.0 < self.row_tolerance <= 1.0 and 0.0 < self.disparity_tolerance <= 1.0):
            raise InvalidInputError(
                f"Expected tolerances in (0, 1], got row {self.row_tolerance}, disparity {self.disparity_tolerance}"
            )
        if not 0.0 <= self.min_consistent_share <= 1.0:
            raise InvalidInputError(f"Expected 0 <= min_consistent_share <= 1, got {self.min_consistent_share}")
        if self.max_keypoints < 0:
            raise InvalidInputError(f"Expected max_keypoints >= 0, got {self.max_keypoints}")
        if self.max_side < 16:
            raise InvalidInputError(f"Expected max_side >= 16 px, got {self.max_side}")


@dataclass(frozen=True)
class FilterResult:
    """The filter's verdict on one pair of halves, with the numbers behind it."""

    outcome: Outcome
    good_matches: int  # left keypoints whose nearest right neighbour passes the ratio test
    keypoints_left: int
    keypoints_right: int
    denominator: str  # what good_match_fraction divides by: always "keypoints_left"
    good_match_fraction: float  # good_matches / keypoints_left, 0.0 when there are no keypoints
    reason: str  # the routing in words, e.g. "review: fraction 0.9 % in [0.5 %, 1.5 %)"
    detect_seconds: float  # SIFT detection + description, both halves
    match_seconds: float  # brute-force kNN matching + ratio test
    consistent_matches: int = 0  # good matches that agree with one stereo geometry (-1: not checked)
    left_size: tuple[int, int] = (0, 0)  # (w, h) px of the left half as given to SIFT
    right_size: tuple[int, int] = (0, 0)
    params: FilterParams = field(default_factory=FilterParams, repr=False)
    points: tuple[np.ndarray, np.ndarray] = field(default=(np.zeros((0, 2)), np.zeros((0, 2))), repr=False)
    """The good matches ``(pts_l, pts_r)``, ``(N, 2)`` float64 px of each half as given (full
    resolution, origin at the top-left pixel centre): later stages reuse them instead of running
    SIFT on the same photos again."""
    match_scale: float = 1.0
    """Half px per SIFT px (>= 1): how much coarser than the halves the matches were found."""

    def metrics(self) -> dict[str, Any]:
        """JSON-safe numbers: counts, fraction, denominator, thresholds, sizes and timings."""
        return {
            "outcome": self.outcome,
            "good_matches": int(self.good_matches),
            "keypoints_left": int(self.keypoints_left),
            "keypoints_right": int(self.keypoints_right),
            "denominator": self.denominator,
            "good_match_fraction": float(self.good_match_fraction),
            "consistent_matches": int(self.consistent_matches),
            "ratio": float(self.params.ratio),
            "cull_fraction": float(self.params.cull_fraction),
            "review_fraction": float(self.params.review_fraction),
            "min_good_matches": int(self.params.min_good_matches),
            "max_side": int(self.params.max_side),
            "max_keypoints": int(self.params.max_keypoints),
            "check_geometry": bool(self.params.check_geometry),
            "row_tolerance": float(self.params.row_tolerance),
            "disparity_tolerance": float(self.params.disparity_tolerance),
            "min_consistent_share": float(self.params.min_consistent_share),
            "left_size": [int(v) for v in self.left_size],
            "right_size": [int(v) for v in self.right_size],
            "detect_seconds": round(float(self.detect_seconds), 6),
            "match_seconds": round(float(self.match_seconds), 6),
        }


def _pct(fraction: float) -> str:
    return f"{100.0 * fraction:.3g} %"


def route(fraction: float, good: int, params: FilterParams, consistent: int | None = None) -> tuple[Outcome, str]:
    """Route a card by its good-match fraction and count; pure, thresholds from ``params``.

    ``good < min_good_matches`` or ``fraction < cull_fraction``: culled; ``fraction <
    review_fraction``: review; otherwise pass. Boundaries belong to the upper class: exactly
    0.005 is review, exactly 0.015 passes, exactly 10 matches is enough. ``consistent`` (good
    matches agreeing with one stereo geometry; ``None``: not checked) below
    ``min_good_matches`` culls, and below ``min_consistent_share`` of ``good`` turns a pass
    into review.
    """
    if not math.isfinite(fraction):
        return "culled", f"culled: fraction is not a number ({fraction})"
    if good < params.min_good_matches:
        return "culled", f"culled: {good} good matches < {params.min_good_matches}"
    if fraction < params.cull_fraction:
        return "culled", f"culled: fraction {_pct(fraction)} < {_pct(params.cull_fraction)}"
    if consistent is not None and consistent < params.min_good_matches:
        return "culled", (
            f"culled: only {consistent} of {good} good matches fit one stereo geometry (< {params.min_good_matches})"
        )
    if fraction < params.review_fraction:
        return "review", (f"review: fraction {_pct(fraction)} in [{_pct(params.cull_fraction)}, {_pct(params.review_fraction)})")
    if consistent is not None and consistent < params.min_consistent_share * good:
        return "review", (
            f"review: fraction {_pct(fraction)} passes, but only {consistent} of {good} good matches "
            f"({_pct(consistent / good)}) fit one stereo geometry (< {_pct(params.min_consistent_share)})"
        )
    return "pass", f"pass: fraction {_pct(fraction)} >= {_pct(params.review_fraction)}"


def consistent_matches(offsets: np.ndarray, params: FilterParams) -> int:
    """How many matches agree with one stereo geometry.

    ``offsets``: ``(n, 2)`` per good match, (right - left) keypoint position in units of each
    half's width and height. A match agrees when its vertical offset is within
    ``row_tolerance`` and its horizontal offset within ``disparity_tolerance`` of the medians;
    none agree when the medians themselves are implausible for two views of one scene framed by
    the split boxes (|horizontal| > 0.3 or |vertical| > 0.1).
    """
    if offsets.shape[0] == 0:
        return 0
    du, dv = offsets[:, 0], offsets[:, 1]
    mu, mv = float(np.median(du)), float(np.median(dv))
    if abs(mu) > 0.3 or abs(mv) > 0.1:
        return 0
    agree = (np.abs(du - mu) <= params.disparity_tolerance) & (np.abs(dv - mv) <= params.row_tolerance)
    return int(np.count_nonzero(agree))


def _prepare(half: np.ndarray, max_side: int) -> np.ndarray:
    """Grey ``uint8`` copy resampled so that its longer side is ``max_side`` (area filter down,
    bicubic up), its contrast stretched (:func:`pipeline.contrast.stretch_contrast`: a faded
    print keeps its keypoints).

    Up as well as down: every half is matched at one working size, so the matches, and the
    thresholds rectification counts in matching px, mean the same fraction of the photo whatever
    the scan's resolution (rectification never lets a tolerance go under one pixel of the scan,
    so halves under 600 px keep their own pixel as the floor). Measured 2026-11-28 with
    ``keystone bench invariance`` on the nine NYPL cards at 1x-4x: variants answering like their
    card at every stage 52 -> 63 of 81, |dy| p95 0.47-2.87 -> 0.42-1.62 px (docs/BENCHMARKS.md)."""
    grey = half if half.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(half), cv2.COLOR_RGB2GRAY)
    height, width = grey.shape
    longer = max(height, width)
    if longer != max_side:
        scale = max_side / longer
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)
    return stretch_contrast(np.ascontiguousarray(grey))


# Relative closeness below which a float32 distance of OpenCV's and a float64 one of ours might
# rank or test differently (a 128-term float32 sum errs by < 1e-5 of its value): such queries
# are matched by cv2.BFMatcher itself.
_UNSURE = 1e-4
_DISTANCE_BLOCK = 8_000_000  # float32 distances computed at once (32 MB)


def ratio_test_matches(descriptors_l: np.ndarray, descriptors_r: np.ndarray, ratio: float) -> list[tuple[int, int]]:
    """``(query, train)`` indices of the left descriptors whose nearest right descriptor passes
    Lowe's ratio test (L2 distance < ``ratio`` x the second nearest's), in query order.

    ``descriptors_l`` ``(N, D)``, ``descriptors_r`` ``(M, D)``: float32 (SIFT's). The same pairs
    as ``cv2.BFMatcher(cv2.NORM_L2).knnMatch(k=2)`` and the test, for a quarter of its CPU time
    (measured on the shared cards, 2,000 x 2,000 SIFT descriptors, one core: 75-80 ms -> 18-23 ms,
    the same good matches on all 14): squared distances from one matrix product
    (``|a|^2 + |b|^2 - 2 a.b``, float32) pick each query's three nearest candidates, whose exact
    distances (float64) decide. A query is handed to ``BFMatcher`` whenever float error could
    matter: a fourth candidate within the product's error bound of the second, or a ratio within
    1e-4 of ``ratio``.
    """
    n_left, n_right = len(descriptors_l), len(descriptors_r)
    if n_left == 0 or n_right < 2:
        return []
    a = np.ascontiguousarray(descriptors_l, np.float32)
    b = np.ascontiguousarray(descriptors_r, np.float32)
    if n_right <= 3:
        return _bf_ratio_matches(a, b, ratio, np.arange(n_left))
    norms_r = np.einsum("ij,ij->i", b, b)
    pairs: dict[int, int] = {}
    unsure: list[np.ndarray] = []
    # Queries in blocks: the (block, M) distance matrix stays under 32 MB whatever the keypoint
    # cap (max_keypoints 0 keeps every keypoint).
    block = max(1, _DISTANCE_BLOCK // n_right)
    for start in range(0, n_left, block):
        good, doubtful, best = _nearest_two_block(a[start : start + block], b, norms_r, ratio)
        pairs.update((start + int(q), int(best[q])) for q in np.flatnonzero(good))
        unsure.append(start + np.flatnonzero(doubtful))
    doubtful_queries = np.concatenate(unsure)
    if doubtful_queries.size:
        pairs.update(_bf_ratio_matches(a, b, ratio, doubtful_queries))
    return sorted(pairs.items())


def _nearest_two_block(
    a: np.ndarray, b: np.ndarray, norms_r: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For queries ``a`` ``(n, D)`` against ``b`` ``(M, D)`` (M > 3, ``norms_r`` = |b|^2): which
    pass the ratio test for sure, which are in doubt (for ``BFMatcher``), and each one's nearest."""
    n = len(a)
    norms_l = np.einsum("ij,ij->i", a, a)
    # (n, M) float32: -2 a.b; the binding takes None for the unused third operand, its stubs do not
    squared = np.asarray(cv2.gemm(a, b, -2.0, None, 0.0, flags=cv2.GEMM_2_T), np.float32)  # type: ignore[call-overload]
    squared += norms_l[:, None]
    squared += norms_r[None, :]
    rows = np.arange(n)
    candidates = np.empty((n, 3), np.intp)
    for k in range(3):
        candidates[:, k] = nearest = squared.argmin(axis=1)
        squared[rows, nearest] = np.inf
    fourth = squared.min(axis=1).astype(np.float64)
    exact = ((a[:, None, :].astype(np.float64) - b[candidates].astype(np.float64)) ** 2).sum(axis=2)
    order = np.argsort(exact, axis=1, kind="stable")
    best = candidates[rows, order[:, 0]]
    first, second = exact[rows, order[:, 0]], exact[rows, order[:, 1]]
    # float32 error of |a|^2 + |b|^2 - 2 a.b: under 2 x 2^-24 x D x the squared norms (loose)
    bound = 2.0 * 2.0**-24 * a.shape[1] * (norms_l.astype(np.float64) + float(norms_r.max())) + 1e-3
    d1, d2 = np.sqrt(first), np.sqrt(second)
    doubtful = (fourth - bound <= second) | (np.abs(d1 - ratio * d2) <= _UNSURE * d2)
    return ~doubtful & (d1 < ratio * d2), doubtful, best


def _bf_ratio_matches(a: np.ndarray, b: np.ndarray, ratio: float, queries: np.ndarray) -> list[tuple[int, int]]:
    """The ratio test's pairs for the left descriptors ``queries`` by ``cv2.BFMatcher`` (exact k=2)."""
    matcher = cv2.BFMatcher(cv2.NORM_L2, crossCheck=False)
    out = []
    for pair in matcher.knnMatch(np.ascontiguousarray(a[queries]), b, k=2):
        if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance:
            out.append((int(queries[pair[0].queryIdx]), pair[0].trainIdx))
    return out


def good_match_fraction(left: np.ndarray, right: np.ndarray, params: FilterParams = FilterParams()) -> FilterResult:
    """SIFT good-match fraction between two halves, and the routing it implies.

    ``left``, ``right``: uint8 ``(H, W)`` or ``(H, W, 3)`` RGB, not empty; they need not be the
    same size. Each is made grey and downscaled to ``params.max_side``. A half without
    keypoints (blank, textureless, too small for SIFT) gives fraction 0.0 and ``culled``, never
    NaN. Timings are wall-clock seconds on whatever OpenCV thread count is set.
    """
    check_image(left, "the left half")
    check_image(right, "the right half")
    grey_left, grey_right = _prepare(left, params.max_side), _prepare(right, params.max_side)

    clock = time.perf_counter()
    sift = cv2.SIFT_create(nfeatures=params.max_keypoints)  # type: ignore[attr-defined]  # cv2's stubs lack the factory
    keypoints_l, descriptors_l = sift.detectAndCompute(grey_left, None)
    keypoints_r, descriptors_r = sift.detectAndCompute(grey_right, None)
    detect_seconds = time.perf_counter() - clock
    n_left, n_right = len(keypoints_l), len(keypoints_r)

    clock = time.perf_counter()
    offsets: list[tuple[float, float]] = []
    pts_l: list[tuple[float, float]] = []
    pts_r: list[tuple[float, float]] = []
    if descriptors_l is not None and descriptors_r is not None and n_left > 0 and n_right >= 2:
        (hl, wl), (hr, wr) = grey_left.shape, grey_right.shape
        for query, train in ratio_test_matches(descriptors_l, descriptors_r, params.ratio):
            (xl, yl), (xr, yr) = keypoints_l[query].pt, keypoints_r[train].pt
            offsets.append((xr / wr - xl / wl, yr / hr - yl / hl))
            pts_l.append((xl, yl))
            pts_r.append((xr, yr))
    good = len(offsets)
    consistent = consistent_matches(np.array(offsets).reshape(-1, 2), params) if params.check_geometry else None
    match_seconds = time.perf_counter() - clock

    fraction = good / n_left if n_left > 0 else 0.0
    if n_left == 0 or n_right == 0:
        where = "either half" if n_left == n_right == 0 else ("the left half" if n_left == 0 else "the right half")
        outcome: Outcome = "culled"
        reason = f"culled: no SIFT keypoints in {where} (blank or textureless)"
    else:
        outcome, reason = route(fraction, good, params, consistent)
    # Pixel centres: x_half + 0.5 = (x_sift + 0.5) / scale, per half and axis.
    to_half = [
        np.array([left.shape[1] / grey_left.shape[1], left.shape[0] / grey_left.shape[0]]),
        np.array([right.shape[1] / grey_right.shape[1], right.shape[0] / grey_right.shape[0]]),
    ]
    points = tuple((np.array(pts, np.float64).reshape(-1, 2) + 0.5) * scale - 0.5 for pts, scale in zip((pts_l, pts_r), to_half))
    return FilterResult(
        points=points,
        match_scale=float(max(to_half[0].max(), to_half[1].max())),
        outcome=outcome,
        good_matches=good,
        keypoints_left=n_left,
        keypoints_right=n_right,
        denominator=DENOMINATOR,
        good_match_fraction=float(fraction),
        reason=reason,
        consistent_matches=-1 if consistent is None else consistent,
        detect_seconds=detect_seconds,
        match_seconds=match_seconds,
        left_size=(int(grey_left.shape[1]), int(grey_left.shape[0])),
        right_size=(int(grey_right.shape[1]), int(grey_right.shape[0])),
        params=params,
    )


def decode_width(params: FilterParams = FilterParams()) -> int:
    """px: the narrowest copy of a card the filter analyses as it does the full card: the split's
    ``analysis_width``, and halves at least 1.125 x ``max_side`` wide (photo boxes fill ~90 % of
    a half), so SIFT still gets ``max_side`` px downscaled from a larger half."""
    return max(params.split.analysis_width, math.ceil(2.25 * params.max_side))


def filter_card(card: np.ndarray, params: FilterParams = FilterParams()) -> tuple[CardSplit, FilterResult]:
    """Split a card at its gutter (:func:`pipeline.split.split_card`) and filter its halves."""
    split = split_card(card, params.split)
    left, right = crop_halves(card, split)
    return split, good_match_fraction(left, right, params)
