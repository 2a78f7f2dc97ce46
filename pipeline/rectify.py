"""Uncalibrated stereo rectification: Loop & Zhang 1999 with KeystoneDepth's changes.

Conventions
-----------
- Images: ``uint8`` ``(H, W)`` grey or ``(H, W, 3)`` RGB (see :mod:`pipeline.io`).
- Pixel coordinates: ``(x, y)`` in px, origin at the **centre of the top-left pixel**, x to the
  right, y down (OpenCV's convention, so ``cv2.warpPerspective`` applies ``H`` unchanged).
- Homographies: 3x3 ``float64``, column-vector convention ``x' ~ H x`` with ``x = (x, y, 1)^T``.
  (KeystoneDepth's ``.mat`` files use the row-vector convention: theirs is ``H^T``.)
- Fundamental matrix: ``x_r^T F x_l = 0`` (``F x_l`` is the epipolar line in the right view).
  Epipoles are unit-norm null vectors from the SVD: ``F e_l = 0``, ``F^T e_r = 0``; nothing here
  ever divides by ``e3`` or by ``F[2, 2]`` (a nearly rectified pair puts the epipole ~1e5 px away
  with a sign that flips between estimators).
- Disparity: ``d = x_l - x_r`` after rectification (``x_right = x_left - d``), ``d >= 0``.

Method (Loop & Zhang, "Computing rectifying homographies for stereo vision", CVPR 1999)
---------------------------------------------------------------------------------------
Each rectifying homography is decomposed as ``H = H_s H_r H_p`` (shearing, similarity,
projective). All steps run in normalised coordinates ``x_n = N x`` (origin at the image centre,
unit ~ half the larger side) so that numbers stay O(1).

1. *Projective* ``H_p = [[1,0,0],[0,1,0],[w_a,w_b,1]]`` sends the line ``w`` to infinity; with
   ``z = (lambda, mu, 0)^T`` the lines are ``w = [e_l]_x z`` (left) and ``w' = F z`` (right), so
   both epipoles go to infinity together. The projective distortion of an image is the
   generalised Rayleigh quotient

       d(z) = (z^T A z) / (z^T B z),  A = [e]_x^T P P^T [e]_x,  B = [e]_x^T p_c p_c^T [e]_x

   (upper-left 2x2 blocks; for the right view ``[e]_x`` is replaced by ``F``), with
   ``P P^T = (w h / 12) diag(w^2 - 1, h^2 - 1, 0)`` the pixel covariance and ``p_c`` the image
   centre. ``z`` minimises the paper's combined criterion ``d_l(z) + d_r(z)``. Here ``B``
   is rank one, ``B = v v^T``, so a single view's optimum is the closed form ``z ~ A^{-1} v``
   (the top generalised eigenvector of ``(B, A)``, i.e. the paper's ``D^{-1} y`` route without a
   Cholesky factor), used only when ``A`` is well conditioned. ``A`` is singular exactly when the
   epipole is at infinity (already rectified), so the combined criterion is minimised over the
   unit circle ``z = (cos t, sin t)`` instead: a dense grid seeded with the closed forms, then a
   bounded scalar refinement. No Cholesky and no inverse of a singular matrix is ever taken.
2. *Similarity* ``H_r``: rotates the (now infinite) epipole onto the x axis (the smaller of the
   two rotations that do so) and, for the right view, scales/shifts y so that corresponding
   rows agree: after ``H_p`` and the rotations ``F ~ [[0,0,0],[0,0,p],[0,q,r]]`` and
   ``y_l = -(p y_r + r) / q`` (the paper's similarity step, derived from the transformed ``F``
   rather than from ``F[2,2]``). A negative row scale means the right view is upside down: it is turned by
   180 deg so that no mirror is ever introduced.
3. *Shearing* ``H_s = [[a, b, 0],[0, 1, 0],[0, 0, 1]]`` keeps the midlines
   ``x = b^ - d^`` and ``y = c^ - a^`` perpendicular and their length ratio at the original
   ``(w - 1) / (h - 1)``: ``a = (h^2 x_v^2 + w^2 y_v^2) / (h w (x_v y_u - x_u y_v))``,
   ``b = (h^2 x_u x_v + w^2 y_u y_v) / (h w (x_u y_v - x_v y_u))``, ``a > 0``, where here ``w``
   and ``h`` stand for ``w - 1`` and ``h - 1`` (the midline lengths between pixel centres, so that
   the identity is exact). Shear changes only x, so rows stay aligned.
4. A common uniform scale keeps the left view's area and a common translation keeps the left
   view's centre, so an already rectified ``F ~ [[0,0,0],[0,0,-1],[0,1,0]]`` gives the identity.

Robust choice (:func:`rectify_pair`): F by USAC MAGSAC++; besides Loop-Zhang, two row alignments
of the right view (left view kept: ``y' = a x + b y + c`` with ``x' = b x - a y``, and the same
over ``g x + h y + 1``) fitted to every match with a MAD-based start and iterated 3-sigma least
squares, so a few gross matches cannot pull them. All candidates are measured (|dy| p95 on the
same number of best-aligned matches, distortion) and the lowest ``|dy| p95 + 0.15 px per degree
of shear and turn`` wins, the simpler model on a tie: on nearly rectified cards F's epipole
direction is loose and Loop-Zhang turns both views by it.

KeystoneDepth's changes (:func:`rectify_pair`): focal length from a 45 deg vertical field of
view, ``f = H / (2 tan 22.5 deg) = 1.2071 H`` with ``H`` the output height (px); principal point at the centre of the full image
where known, else the output centre; the right view is translated so that no inlier disparity is
negative. Both rectified views share ``K``; the rectified relative pose is ``R = I``,
``t = (-1, 0, 0)`` (unit baseline, ``X_r = R X_l + t``). The pose of the *original* cameras is not
derived: Loop-Zhang homographies include shear and scale, so they are not ``K R K^-1``.

Gates raise :class:`RectificationError` subclasses with stable codes: ``too_few_matches``,
``planar_or_far_scene``, ``epipole_in_image``, ``mirrored_pair``, ``upside_down_view``, ``distortion_beyond_limits``,
``residual_dy_too_large``, ``unbounded_warp``; invalid arrays raise
:class:`pipeline.errors.InvalidInputError`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from scipy.optimize import minimize_scalar

from .contracts import check_image
from .contrast import stretch_contrast
from .errors import InvalidInputError, PipelineError

__all__ = [
    "FOCAL_PER_HEIGHT",
    "DistortionError",
    "EpipoleInImageError",
    "MirroredPairError",
    "PlanarSceneError",
    "Rectification",
    "RectificationError",
    "RectifyParams",
    "ResidualDyError",
    "TooFewMatchesError",
    "UnboundedWarpError",
    "UpsideDownError",
    "distortion_metrics",
    "epipoles",
    "estimate_fundamental",
    "loop_zhang",
    "match_features",
    "photograph_mask",
    "rectify_matches",
    "rectify_pair",
    "scale_rectification",
    "scaling_matrix",
    "stored_view_scale",
    "warp_pair",
]

FOCAL_PER_HEIGHT = 1.0 / (2.0 * math.tan(math.radians(22.5)))  # 1.2071: 45 deg vertical FOV
MIN_SIDE = 16  # px: smaller views cannot be rectified (SIFT finds nothing useful)


# ------------------------------------------------------------------------------------ errors


class RectificationError(PipelineError):
    """Rectification refused this pair; ``code`` says which gate."""

    code = "rectification_failed"


class TooFewMatchesError(RectificationError):
    """Fewer SIFT matches or fundamental-matrix inliers than the parameters require."""

    code = "too_few_matches"


class PlanarSceneError(RectificationError):
    """A homography explains (almost) every match: F is degenerate, the epipole arbitrary."""

    code = "planar_or_far_scene"


class EpipoleInImageError(RectificationError):
    """An epipole lies inside or near an image: rectification would be unbounded."""

    code = "epipole_in_image"


class MirroredPairError(RectificationError):
    """The right view is a mirror image of the left (x runs backwards): not a stereo pair."""

    code = "mirrored_pair"


class UpsideDownError(RectificationError):
    """One view is turned 180 deg relative to the other: the orientation step must fix it first."""

    code = "upside_down_view"


class DistortionError(RectificationError):
    """Midline angle, aspect change or kept fraction beyond the limits."""

    code = "distortion_beyond_limits"


class ResidualDyError(RectificationError):
    """Inliers still differ in row after rectification by more than the limit."""

    code = "residual_dy_too_large"


class UnboundedWarpError(RectificationError):
    """The warp would need an output canvas beyond the bound (or non-finite homographies)."""

    code = "unbounded_warp"


# ------------------------------------------------------------------------------------ params


@dataclass(frozen=True)
class RectifyParams:
    """Parameters of :func:`rectify_pair` (px are of the views as given unless stated)."""

    ratio: float = 0.7
    """Lowe ratio test on SIFT descriptors (the paper's value)."""
    max_keypoints: int = 4000
    """SIFT keeps at most this many keypoints per view, the strongest."""
    max_side: int = 800
    """px: the working resolution. Views are downscaled (area filter) to this longer side for SIFT
    only; matches are mapped back to full-resolution pixel coordinates, so the homographies are
    estimated at full resolution. Measured on the six shared real pairs with views over 800 px
    (``benchmarks/rectify_real.py --max-side``): fresh-match |dy| p95 at full resolution the same
    at 800 as at 1200 (-0.06 to +0.03 px), rectification CPU time 27-44 % lower (one thread)."""
    min_matches: int = 12
    """Fewer ratio-test matches: ``too_few_matches``."""
    min_inliers: int = 10
    """Fewer fundamental-matrix inliers: ``too_few_matches``."""
    f_threshold: float = 1.0
    """px: MAGSAC inlier threshold for the fundamental matrix (at the SIFT scale)."""
    h_threshold: float = 1.0
    """px: RANSAC inlier threshold for the competing homography (at the SIFT scale). The same
    as F's, so that the two models are compared like for like: with a looser H threshold, real
    far scenes with 2-3 px of parallax (4 of 12 shared real cards) read as planar."""
    disparity_fence: float = 5.0
    """Inliers of F whose disparity lies more than this many robust sigmas (1.4826 x MAD, at
    least 1 % of the view width) from the median are along-row mismatches: they fit the epipolar
    geometry but not the scene, and are left out of the disparity range and the translation."""
    planar_ratio: float = 0.9
    """Homography inliers >= this x F inliers: ``planar_or_far_scene``."""
    skip_dy_tolerance: float = 1.0
    """px: the pair counts as already rectified when the p95 of |dy| over the matches that fit
    ``F0 = [[0,0,0],[0,0,-1],[0,1,0]]`` is below this ..."""
    skip_share: float = 0.9
    """... and those matches are at least this share of the fundamental-matrix inliers."""
    epipole_margin: float = 1.5
    """Epipole closer to the image centre than this x the half-diagonal: ``epipole_in_image``."""
    max_midline_deviation: float = 10.0
    """deg: largest |midline angle - 90| after rectification."""
    max_aspect_change: float = 1.5
    """Largest aspect change (ratio, either direction: 1.5 means 2/3 .. 3/2)."""
    max_row_scale_change: float = 0.03
    """Row alignment of a nearly rectified pair may rescale y by at most this (a zoom is not one)."""
    max_rotation: float = 10.0
    """deg: largest in-plane rotation of a view. Stereo cameras of the period were levelled, so
    a view turned further is the symptom of a wrong F (a near-planar scene), not of the scene."""
    min_kept_fraction: float = 0.5
    """Smallest fraction of each view's warped area inside the output canvas."""
    max_dy_p95: float = 2.0
    """px: largest inlier |dy| p95 after rectification: else ``residual_dy_too_large``."""
    max_canvas_scale: float = 2.0
    """The output canvas is at most this x the input size in each dimension."""
    max_output_pixels: int = 150_000_000
    """Refuse warps whose output canvas has more pixels than this (unbounded warp)."""
    detect_swapped: bool = False
    """Swap the views when the median inlier disparity (x_l - x_r, in the views' own
    coordinates, carried through rectification) is negative. Off in the pipeline: the eye
    order cannot be read from that sign (the horizontal offset between two photos on a card is
    arbitrary, and crop alignment puts far content at zero), so it is decided before
    rectification by the orientation step, the crowd or a curator (``pipeline.decided_orientation``) and
    never overridden here. Kept for pairs known to be cropped views with content in front of
    infinity."""
    random_seed: int = 0
    """USAC random generator state: same input, same F."""
    work_side: int | None = 800
    """px: the rectify stage stores the rectified views at most this long on their longer side
    (:func:`stored_view_scale`), and the disparity stage works on them at that size; ``None``
    keeps the full resolution (the behaviour before the working resolution). The homographies
    still take the full-resolution crops as input. Chosen by ``keystone bench workres`` (disparity
    error against CPU time across working sides, docs/BENCHMARKS.md): on ground-truth scenes
    scanned at 2x (1482x1000 views, as a ~3000 px card's), mean bad-2 15.7 % at 800 against
    17.6 % at full resolution, in 0.31 s against 1.02 s; 1000 and full are dominated by 800, and
    600 (17.8 %, 0.17 s) loses 1.5-2 points on scenes given at their own ~740 px resolution,
    the size of a Keystone-Mast raw scan's views."""

    def __post_init__(self) -> None:
        if not 0.0 < self.ratio <= 1.0:
            raise InvalidInputError(f"Expected 0 < ratio <= 1, got {self.ratio}")
        if self.max_side < MIN_SIDE or self.max_keypoints < 0:
            raise InvalidInputError(f"Expected max_side >= {MIN_SIDE} and max_keypoints >= 0")
        if self.min_inliers < 8 or self.min_matches < self.min_inliers:
            raise InvalidInputError(f"Expected 8 <= min_inliers <= min_matches, got {self.min_inliers}, {self.min_matches}")
        for name in ("f_threshold", "h_threshold", "skip_dy_tolerance", "max_dy_p95", "max_midline_deviation"):
            if not getattr(self, name) > 0:
                raise InvalidInputError(f"Expected {name} > 0, got {getattr(self, name)}")
        if not (0.0 < self.planar_ratio <= 1.0 and 0.0 < self.skip_share <= 1.0 and 0.0 <= self.min_kept_fraction <= 1.0):
            raise InvalidInputError("Expected planar_ratio, skip_share in (0, 1] and min_kept_fraction in [0, 1]")
        if self.max_aspect_change < 1.0 or self.max_canvas_scale < 1.0 or self.epipole_margin < 0:
            raise InvalidInputError("Expected max_aspect_change >= 1, max_canvas_scale >= 1, epipole_margin >= 0")
        if self.work_side is not None and (isinstance(self.work_side, bool) or self.work_side < MIN_SIDE):
            raise InvalidInputError(f"Expected work_side None or >= {MIN_SIDE} px, got {self.work_side!r}")


# ------------------------------------------------------------------------------------ result


@dataclass(frozen=True)
class Rectification:
    """A rectification of one pair, in the conventions of the module docstring.

    ``H_l`` / ``H_r`` map the pixels of the views that end up left / right (after a swap,
    ``H_l`` applies to the view given as ``right``). ``size`` is the output ``(width, height)``
    px of both rectified views. ``K`` is the shared intrinsic matrix of the rectified views (px),
    ``R``, ``t`` the rectified relative pose (``X_r = R X_l + t``, unit baseline).
    ``disparity_range`` is (min, max) of inlier ``x_l - x_r`` after rectification (px).
    ``warp_needed`` is False when the pair was already rectified within tolerance (identity
    homographies; ``reason`` says so).
    """

    H_l: np.ndarray
    H_r: np.ndarray
    size: tuple[int, int]
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    disparity_range: tuple[float, float]
    dy_median: float  # px, inlier |y_l - y_r| after rectification
    dy_p95: float  # px
    midline_angle: float  # deg, the worse of the two views (90 = no shear)
    aspect_change: float  # ratio >= 1, the worse view: max(r, 1/r) of midline length ratio after/before
    shear: float  # |cos(midline angle)|, the worse view
    kept_fraction: float  # smallest fraction of a view's warped area inside the canvas
    matches: int
    inliers: int
    swapped: bool
    warp_needed: bool
    reason: str
    seconds: float = 0.0
    rotation: float = 0.0  # deg, the larger in-plane rotation of the two views
    method: str = "loop_zhang"
    """``identity`` (already rectified), ``loop_zhang``, ``row_affine`` or ``row_projective``."""
    F: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)), repr=False)
    """The fundamental matrix used (views in output order: ``x_r^T F x_l = 0``, unit norm)."""
    inlier_points: tuple[np.ndarray, np.ndarray] = field(default=(np.zeros((0, 2)), np.zeros((0, 2))), repr=False)
    """Inlier matches ``(pts_l, pts_r)`` (N, 2) px in the (swapped if so) input views."""
    view_scale: float = 1.0
    """Rectified-view px per full-resolution rectified px (:func:`scale_rectification`): 1 for
    the full-resolution frame; below 1 the outputs (``H_l``, ``H_r``, ``size``, ``K``,
    disparity range, |dy|) are those of views stored at that scale, and :func:`warp_pair`
    downscales the inputs (area filter) before warping so the views are not aliased."""

    def metrics(self) -> dict[str, Any]:
        """JSON-safe numbers for a StageRecord (homographies as nested lists, row = row of H)."""
        return {
            "H_l": np.asarray(self.H_l, float).tolist(),
            "H_r": np.asarray(self.H_r, float).tolist(),
            "size": [int(v) for v in self.size],
            "K": np.asarray(self.K, float).tolist(),
            "R": np.asarray(self.R, float).tolist(),
            "t": np.asarray(self.t, float).tolist(),
            "disparity_min": float(self.disparity_range[0]),
            "disparity_max": float(self.disparity_range[1]),
            "dy_median": float(self.dy_median),
            "dy_p95": float(self.dy_p95),
            "midline_angle": float(self.midline_angle),
            "aspect_change": float(self.aspect_change),
            "shear": float(self.shear),
            "kept_fraction": float(self.kept_fraction),
            "matches": int(self.matches),
            "inliers": int(self.inliers),
            "swapped": bool(self.swapped),
            "warp_needed": bool(self.warp_needed),
            "reason": self.reason,
            "seconds": round(float(self.seconds), 4),
            "rotation": round(float(self.rotation), 3),
            "method": self.method,
            "view_scale": float(self.view_scale),
        }


# ---------------------------------------------------------------------------------- matching


def _grey_scaled(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    grey = image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    height, width = grey.shape
    scale = min(1.0, max_side / max(height, width))
    if scale < 1.0:
        grey = cv2.resize(grey, (max(1, round(width * scale)), max(1, round(height * scale))), interpolation=cv2.INTER_AREA)
        scale = grey.shape[1] / width  # the scale actually applied in x (y within a pixel)
    # As the filter's: a faded print keeps its keypoints (pipeline.contrast).
    return stretch_contrast(np.ascontiguousarray(grey)), scale


def _check_view(image: object, name: str) -> np.ndarray:
    if isinstance(image, np.ndarray) and image.dtype.kind == "f" and not np.all(np.isfinite(image)):
        raise InvalidInputError(f"Expected finite pixel values in {name}, got NaN or inf")
    return check_image(image, name, MIN_SIDE, MIN_SIDE)


def match_features(left: np.ndarray, right: np.ndarray, params: RectifyParams = RectifyParams()) -> tuple[np.ndarray, np.ndarray]:
    """SIFT matches between two views, Lowe ratio test ``params.ratio`` [0.7].

    ``left``, ``right``: uint8 ``(H, W)`` / ``(H, W, 3)``, at least 16 x 16 px. SIFT runs on grey
    copies downscaled to ``params.max_side`` with at most ``params.max_keypoints`` keypoints;
    matching is exact brute force (deterministic). Returns ``pts_l``, ``pts_r``: ``(N, 2)``
    float64 full-resolution px (origin at the top-left pixel centre); ``N`` may be 0. Each right
    keypoint is used at most once (the closest left query wins).
    """
    _check_view(left, "the left view")
    _check_view(right, "the right view")
    grey_l, scale_l = _grey_scaled(left, params.max_side)
    grey_r, scale_r = _grey_scaled(right, params.max_side)
    sift = cv2.SIFT_create(nfeatures=params.max_keypoints)  # type: ignore[attr-defined]  # cv2's stubs lack the factory
    kp_l, des_l = sift.detectAndCompute(grey_l, None)
    kp_r, des_r = sift.detectAndCompute(grey_r, None)
    empty = np.zeros((0, 2), np.float64)
    if des_l is None or des_r is None or len(kp_l) < 1 or len(kp_r) < 2:
        return empty, empty.copy()
    best: dict[int, tuple[float, int]] = {}
    for pair in cv2.BFMatcher(cv2.NORM_L2).knnMatch(des_l, des_r, k=2):
        if len(pair) == 2 and pair[0].distance < params.ratio * pair[1].distance:
            m = pair[0]
            if m.trainIdx not in best or m.distance < best[m.trainIdx][0]:
                best[m.trainIdx] = (m.distance, m.queryIdx)
    if not best:
        return empty, empty.copy()
    order = sorted(best.items(), key=lambda item: item[1][1])  # by left keypoint index: deterministic
    pts_l = np.array([kp_l[q].pt for _, (_, q) in order], np.float64)
    pts_r = np.array([kp_r[t].pt for t, _ in order], np.float64)
    # Pixel centres: x_full + 0.5 = (x_small + 0.5) / scale.
    return (pts_l + 0.5) / scale_l - 0.5, (pts_r + 0.5) / scale_r - 0.5


# ------------------------------------------------------------------------------------- F, H


def _sampson(F: np.ndarray, pts_l: np.ndarray, pts_r: np.ndarray) -> np.ndarray:
    xl = np.c_[pts_l, np.ones(len(pts_l))]
    xr = np.c_[pts_r, np.ones(len(pts_r))]
    Fx = xl @ F.T
    Ftx = xr @ F
    num = np.sum(xr * Fx, axis=1) ** 2
    den = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
    return num / np.maximum(den, 1e-300)


def estimate_fundamental(
    pts_l: np.ndarray, pts_r: np.ndarray, params: RectifyParams = RectifyParams(), scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray, int]:
    """Robust fundamental matrix with USAC MAGSAC++, and the homography degeneracy gate.

    ``pts_l``, ``pts_r``: ``(N, 2)`` float64 px. ``scale``: px per SIFT px (thresholds in
    ``params`` are at the SIFT scale). Returns ``F`` (3x3, ``x_r^T F x_l = 0``, unit Frobenius
    norm, **not** normalised by ``F[2,2]``), the ``(N,)`` bool inlier mask and the number of
    inliers of a RANSAC homography fit. Raises :class:`TooFewMatchesError` (fewer than
    ``min_matches`` matches or ``min_inliers`` inliers, or no F at all) and
    :class:`PlanarSceneError` when the homography explains at least ``planar_ratio`` x as many
    matches as F (planar or far scene: F is then degenerate with an arbitrary epipole).
    """
    n = len(pts_l)
    if n < params.min_matches:
        raise TooFewMatchesError(f"{n} matches < {params.min_matches}")
    F, mask = _fit_f(pts_l, pts_r, params, scale)
    n_f = int(mask.sum())
    if n_f < params.min_inliers:
        raise TooFewMatchesError(f"{n_f} fundamental-matrix inliers < {params.min_inliers} (of {n} matches)")
    n_h = _homography_inliers(pts_l, pts_r, params, scale)
    if n_h >= params.planar_ratio * n_f:
        raise PlanarSceneError(
            f"a homography explains {n_h} matches vs {n_f} for F (>= {params.planar_ratio:.0%}): "
            "planar or far scene, the epipole is undetermined"
        )
    return F, mask, n_h


def _fit_f(pts_l: np.ndarray, pts_r: np.ndarray, params: RectifyParams, scale: float) -> tuple[np.ndarray, np.ndarray]:
    usac = cv2.UsacParams()
    usac.confidence = 0.999
    usac.maxIterations = 5000
    usac.threshold = params.f_threshold * scale
    usac.randomGeneratorState = params.random_seed
    usac.isParallel = False
    usac.loMethod = cv2.LOCAL_OPTIM_SIGMA
    usac.score = cv2.SCORE_METHOD_MAGSAC
    usac.sampler = cv2.SAMPLING_UNIFORM
    usac.final_polisher = cv2.MAGSAC
    usac.final_polisher_iterations = 10
    usac.loIterations = 10
    usac.loSampleSize = 14
    try:
        F, mask = cv2.findFundamentalMat(np.ascontiguousarray(pts_l, np.float64), np.ascontiguousarray(pts_r, np.float64), usac)
    except cv2.error as exc:
        raise TooFewMatchesError(f"no fundamental matrix: {str(exc).strip().splitlines()[-1][:120]}") from exc
    if F is None or F.shape != (3, 3) or mask is None or not np.all(np.isfinite(F)):
        raise TooFewMatchesError(f"no fundamental matrix from {len(pts_l)} matches")
    F = F / np.linalg.norm(F)
    mask = mask.ravel().astype(bool)
    if mask.sum() >= 8:  # least-squares polish on the inliers (normalised 8-point) when it fits better
        refit, _ = cv2.findFundamentalMat(pts_l[mask], pts_r[mask], cv2.FM_8POINT)
        if refit is not None and refit.shape == (3, 3) and np.all(np.isfinite(refit)) and np.linalg.norm(refit) > 0:
            refit = refit / np.linalg.norm(refit)
            if np.median(_sampson(refit, pts_l[mask], pts_r[mask])) < np.median(_sampson(F, pts_l[mask], pts_r[mask])):
                F = refit
    return F, mask


def _homography_inliers(pts_l: np.ndarray, pts_r: np.ndarray, params: RectifyParams, scale: float) -> int:
    cv2.setRNGSeed(params.random_seed)
    H, mask = cv2.findHomography(pts_l, pts_r, cv2.RANSAC, params.h_threshold * scale, maxIters=5000, confidence=0.999)
    if H is None or mask is None:
        return 0
    return int(mask.sum())


def epipoles(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit-norm epipoles ``e_l`` (``F e_l = 0``) and ``e_r`` (``F^T e_r = 0``), homogeneous,
    from the SVD of ``F`` (the right / left singular vectors of the smallest singular value)."""
    u, _, vt = np.linalg.svd(F)
    return vt[2] / np.linalg.norm(vt[2]), u[:, 2] / np.linalg.norm(u[:, 2])


def _epipole_near(e: np.ndarray, width: int, height: int, margin: float) -> bool:
    """Is the epipole within ``margin`` half-diagonals of the image centre? No division by e3:
    ``|e_xy - c e3| < margin r |e3|``."""
    c = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    r = 0.5 * math.hypot(width, height)
    return bool(np.linalg.norm(e[:2] - c * e[2]) < margin * r * abs(e[2]))


# --------------------------------------------------------------------------------- Loop-Zhang


def _cross(e: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -e[2], e[1]], [e[2], 0.0, -e[0]], [-e[1], e[0], 0.0]])


def _normaliser(width: int, height: int, s: float) -> np.ndarray:
    return np.array([[1 / s, 0, -(width - 1) / (2 * s)], [0, 1 / s, -(height - 1) / (2 * s)], [0, 0, 1.0]])


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``(N, 2)`` points through ``H``; rows at infinity come back as inf (never NaN silently)."""
    xh = np.c_[pts, np.ones(len(pts))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        out = xh[:, :2] / xh[:, 2:3]
    return np.where(np.isfinite(out), out, np.inf)


def _midpoints(width: int, height: int) -> np.ndarray:
    """The paper's a, b, c, d: midpoints of the top, right, bottom and left edges (px)."""
    w1, h1 = width - 1.0, height - 1.0
    return np.array([[w1 / 2, 0.0], [w1, h1 / 2], [w1 / 2, h1], [0.0, h1 / 2]])


def _shear(H: np.ndarray, width: int, height: int) -> np.ndarray:
    """Loop-Zhang shearing ``H_s`` for the view ``width`` x ``height`` under ``H``."""
    a, b, c, d = _apply(H, _midpoints(width, height))
    (xu, xv), (yu, yv) = b - d, c - a
    w, h = width - 1.0, height - 1.0
    den = h * w * (xv * yu - xu * yv)
    if not np.all(np.isfinite([xu, xv, yu, yv])) or abs(den) < 1e-12 * (h * w) * (xu * xu + xv * xv + yu * yu + yv * yv):
        raise DistortionError("the midlines collapse under the projective step (degenerate shear)")
    sa = (h * h * xv * xv + w * w * yv * yv) / den
    sb = (h * h * xu * xv + w * w * yu * yv) / -den
    if sa < 0:
        sa, sb = -sa, -sb
    return np.array([[sa, sb, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _cost_at(theta: float, views: tuple[tuple[np.ndarray, np.ndarray], ...]) -> float:
    """:func:`_projective_z`'s distortion cost at the angle ``theta`` (rad): the sum over the views
    ``(A, v)`` of ``z^T A z / (v . z)^2`` with ``z = (cos, sin)``; inf where ``(v . z)^2`` vanishes
    against ``trace(A) + v . v``. The refinement minimises this form."""
    z = np.array([math.cos(theta), math.sin(theta)])
    total = 0.0
    for a, v in views:
        den = float(v @ z) ** 2
        num = float(z @ a @ z)
        scale = float(np.trace(a)) + float(v @ v)
        if den <= 1e-18 * max(scale, 1e-300):
            return math.inf
        total += num / den
    return total


def _costs_at(thetas: np.ndarray, views: tuple[tuple[np.ndarray, np.ndarray], ...]) -> np.ndarray:
    """:func:`_cost_at` at every angle of ``thetas`` (rad) at once: one array pass over the 722
    starting angles instead of a Python call each (0.1 instead of 12 ms a rectification). The
    values agree with the scalar form to ~1e-10 relative, not to the bit (numpy's dot fuses
    multiply-adds), and pick the same starting angle (3,000 random geometries, and the 15 real
    pairs); the refinement evaluates the scalar form."""
    c, s = np.cos(thetas), np.sin(thetas)
    total = np.zeros(thetas.shape)
    for a, v in views:
        den = (v[0] * c + v[1] * s) ** 2
        num = (c * a[0, 0] + s * a[1, 0]) * c + (c * a[0, 1] + s * a[1, 1]) * s  # z^T A z, as z @ A @ z
        scale = float(np.trace(a)) + float(v @ v)
        with np.errstate(divide="ignore", invalid="ignore"):
            total = total + np.where(den <= 1e-18 * max(scale, 1e-300), np.inf, num / den)
    return total


def _projective_z(F: np.ndarray, e_l: np.ndarray, size_l: tuple[int, int], size_r: tuple[int, int], s: float) -> np.ndarray:
    """The paper's ``z = (lambda, mu, 0)`` minimising the combined projective distortion (normalised
    coordinates, image centre at the origin so ``p_c = (0, 0, 1)``)."""

    def pp(width: int, height: int) -> np.ndarray:  # P P^T / (w h) in normalised units
        return np.diag([(width * width - 1) / 12.0, (height * height - 1) / 12.0, 0.0]) / (s * s)

    ex = _cross(e_l)[:, :2]
    fz = F[:, :2]
    a_l, a_r = ex.T @ pp(*size_l) @ ex, fz.T @ pp(*size_r) @ fz
    v_l, v_r = ex[2], fz[2]  # B = v v^T with v = M^T p_c, p_c = (0, 0, 1)

    views = ((a_l, v_l), (a_r, v_r))

    def cost(theta: float) -> float:
        return _cost_at(theta, views)

    candidates = list(np.linspace(0.0, math.pi, 721)[:-1])
    for a, v in views:  # single-view optima z ~ A^-1 v where A is well conditioned
        if np.linalg.cond(a) < 1e10:
            z = np.linalg.solve(a, v)
            candidates.append(math.atan2(z[1], z[0]) % math.pi)
    costs = _costs_at(np.asarray(candidates), views)
    if not np.any(np.isfinite(costs)):
        raise EpipoleInImageError("no line can be sent to infinity without infinite distortion (epipole at the centre)")
    best = float(candidates[int(np.argmin(costs))])
    step = math.pi / 720
    res = minimize_scalar(cost, bounds=(best - step, best + step), method="bounded", options={"xatol": 1e-10})
    theta = float(res.x) if np.isfinite(res.fun) and res.fun <= cost(best) else best
    return np.array([math.cos(theta), math.sin(theta), 0.0])


def _rotation_to_x(direction: np.ndarray) -> np.ndarray:
    """The smaller rotation taking the line direction ``(dx, dy)`` onto the x axis."""
    phi = math.atan2(direction[1], direction[0])
    phi = (phi + math.pi / 2) % math.pi - math.pi / 2  # direction of a line: modulo pi
    c, s_ = math.cos(phi), math.sin(phi)
    return np.array([[c, s_, 0.0], [-s_, c, 0.0], [0.0, 0.0, 1.0]])


def loop_zhang(
    F: np.ndarray, width: int, height: int, width_r: int | None = None, height_r: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Loop-Zhang rectifying homographies ``(H_l, H_r)`` for ``F`` (``x_r^T F x_l = 0``).

    ``width`` x ``height``: the left view in px (the right view the same unless
    ``width_r``/``height_r`` are given). Returns 3x3 float64 homographies in pixel coordinates
    (column vectors) after which epipolar lines are rows: ``y_l' = y_r'`` for every
    correspondence. Common uniform scale keeps the left view's area, common translation keeps its
    centre: an already rectified ``F`` gives identities. Raises :class:`EpipoleInImageError` for
    an epipole at a view's centre, :class:`DistortionError` for degenerate geometry.
    """
    F = np.asarray(F, np.float64)
    if F.shape != (3, 3) or not np.all(np.isfinite(F)) or np.linalg.norm(F) == 0:
        raise InvalidInputError(f"Expected a finite non-zero 3x3 F, got {F!r}")
    wr, hr = width_r or width, height_r or height
    s = 0.5 * max(width, height, wr, hr)
    n_l, n_r = _normaliser(width, height, s), _normaliser(wr, hr, s)
    Fn = np.linalg.inv(n_r).T @ F @ np.linalg.inv(n_l)
    Fn /= np.linalg.norm(Fn)
    e_l, e_r = epipoles(Fn)

    # 1. projective: send w = [e_l]_x z and w' = F z to infinity.
    z = _projective_z(Fn, e_l, (width, height), (wr, hr), s)
    w_l, w_r = _cross(e_l) @ z, Fn @ z
    if abs(w_l[2]) < 1e-12 * np.linalg.norm(w_l) or abs(w_r[2]) < 1e-12 * np.linalg.norm(w_r):
        raise EpipoleInImageError("the line sent to infinity passes through the image centre")
    hp_l = np.array([[1, 0, 0], [0, 1, 0], w_l / w_l[2]], np.float64)
    hp_r = np.array([[1, 0, 0], [0, 1, 0], w_r / w_r[2]], np.float64)

    # 2. similarity: epipoles (now at infinity, (e1, e2, 0)) onto the x axis, then rows agree.
    r_l, r_r = _rotation_to_x(e_l[:2]), _rotation_to_x(e_r[:2])
    m_l, m_r = r_l @ hp_l, r_r @ hp_r
    f2 = np.linalg.inv(m_r).T @ Fn @ np.linalg.inv(m_l)
    f2 /= np.linalg.norm(f2)
    p, q, r = f2[1, 2], f2[2, 1], f2[2, 2]
    if abs(q) < 1e-9 or abs(p) < 1e-9:
        raise DistortionError("rows cannot be matched: the transformed F is degenerate")
    row_scale = -p / q
    flip = -1.0 if row_scale < 0 else 1.0  # upside-down right view: turn it 180 deg, never mirror
    t_r = np.array([[flip, 0, 0], [0, row_scale, -r / q], [0, 0, 1.0]])
    m_r = t_r @ m_r

    # 3. shearing, per view, in pixel coordinates of the view.
    h_l, h_r = m_l @ n_l, m_r @ n_r
    h_l = _shear(h_l, width, height) @ h_l
    h_r = _shear(h_r, wr, hr) @ h_r

    # 4. common uniform scale (left area kept) and translation (left centre kept).
    corners = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], np.float64)
    quad = _apply(h_l, corners)
    area = abs(cv2.contourArea(quad.astype(np.float32))) if np.all(np.isfinite(quad)) else 0.0
    if not area > 0:
        raise DistortionError("the left view collapses under the rectifying homography")
    k = math.sqrt((width - 1) * (height - 1) / area)
    centre = np.array([[(width - 1) / 2.0, (height - 1) / 2.0]])
    scaled = np.diag([k, k, 1.0])
    moved = _apply(scaled @ h_l, centre)[0]
    common = np.array([[1, 0, centre[0, 0] - moved[0]], [0, 1, centre[0, 1] - moved[1]], [0, 0, 1.0]]) @ scaled
    h_l, h_r = common @ h_l, common @ h_r
    h_l, h_r = h_l / h_l[2, 2] if abs(h_l[2, 2]) > 1e-12 else h_l, h_r / h_r[2, 2] if abs(h_r[2, 2]) > 1e-12 else h_r
    if not (np.all(np.isfinite(h_l)) and np.all(np.isfinite(h_r))):
        raise UnboundedWarpError("non-finite rectifying homography")
    # Orientation: no mirror, x grows left to right, y down, in both views.
    for name, h in (("left", h_l), ("right", h_r)):
        jac = _jacobian(h, centre[0] if name == "left" else np.array([(wr - 1) / 2.0, (hr - 1) / 2.0]))
        if not np.linalg.det(jac) > 0:
            raise MirroredPairError(f"the {name} rectifying homography would mirror the view")
        if jac[0, 0] <= 0 or jac[1, 1] <= 0:
            raise UpsideDownError(
                f"the {name} view is turned over relative to the other (x or y would run backwards): fix its orientation first"
            )
    return h_l, h_r


def _jacobian(H: np.ndarray, point: np.ndarray) -> np.ndarray:
    """2x2 derivative of the homography at ``point`` (px)."""
    x = np.array([point[0], point[1], 1.0])
    u = H @ x
    return (H[:2, :2] * u[2] - np.outer(u[:2], H[2, :2])) / (u[2] * u[2])


# ------------------------------------------------------------------------------------ metrics


def distortion_metrics(H: np.ndarray, width: int, height: int) -> dict[str, float]:
    """Distortion of a view ``width`` x ``height`` under ``H``: ``midline_angle`` (deg between the
    images of the horizontal and vertical midlines; 90 = no shear), ``aspect_change`` (ratio of
    midline lengths after / before, >= 1 either way), ``shear`` (|cos| of the midline angle),
    ``rotation`` (deg of the image of the horizontal midline from the x axis, in (-180, 180])."""
    a, b, c, d = _apply(H, _midpoints(width, height))
    x, y = b - d, c - a
    nx, ny = float(np.linalg.norm(x)), float(np.linalg.norm(y))
    if not (np.isfinite(nx) and np.isfinite(ny)) or nx == 0 or ny == 0:
        return {"midline_angle": 0.0, "aspect_change": math.inf, "shear": 1.0, "rotation": 0.0}
    cosine = float(np.clip(abs(x @ y) / (nx * ny), 0.0, 1.0))
    ratio = (nx / ny) / ((width - 1.0) / max(height - 1.0, 1.0))
    return {
        "midline_angle": math.degrees(math.acos(cosine)),
        "aspect_change": max(ratio, 1.0 / ratio),
        "shear": cosine,
        "rotation": math.degrees(math.atan2(float(x[1]), float(x[0]))),
    }


def _quad(H: np.ndarray, width: int, height: int) -> np.ndarray:
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    return _apply(H, corners)


def _dy_stats(H_l: np.ndarray, H_r: np.ndarray, pts_l: np.ndarray, pts_r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rectified ``dy = y_l' - y_r'`` and ``d = x_l' - x_r'`` of the matches (px)."""
    a, b = _apply(H_l, pts_l), _apply(H_r, pts_r)
    return a[:, 1] - b[:, 1], a[:, 0] - b[:, 0]


def _f0_inliers(pts_l: np.ndarray, pts_r: np.ndarray, tol: float) -> np.ndarray:
    return np.abs(pts_l[:, 1] - pts_r[:, 1]) <= tol


def _disparity_keep(disp: np.ndarray, width: int, fence: float) -> np.ndarray:
    """Bool mask of disparities within ``fence`` robust sigmas (1.4826 MAD, at least 1 % of the
    width) of the median: the rest are along-row mismatches."""
    med = float(np.median(disp))
    sigma = max(1.4826 * float(np.median(np.abs(disp - med))), 0.01 * width)
    keep = np.abs(disp - med) <= fence * sigma
    return keep if keep.any() else np.ones(len(disp), bool)


def _check_not_mirrored(xl: np.ndarray, xr: np.ndarray) -> None:
    if len(xl) >= 3 and np.std(xl) > 0 and np.std(xr) > 0 and np.corrcoef(xl, xr)[0, 1] < 0:
        raise MirroredPairError("x runs backwards in the right view relative to the left (a mirror image)")


# ------------------------------------------------------------------------------------- pairs


def rectify_pair(
    left: np.ndarray,
    right: np.ndarray,
    params: RectifyParams = RectifyParams(),
    principal_point: tuple[float, float] | None = None,
) -> Rectification:
    """Rectify a stereo pair: matches, F, gates, Loop-Zhang, KeystoneDepth's changes.

    ``left``, ``right``: uint8 ``(H, W)`` / ``(H, W, 3)`` views, at least 16 x 16 px, any sizes.
    ``principal_point``: (x, y) px of the centre of the full image in left-view pixels, where
    known; else the output canvas centre. Order of decisions:

    1. matches (< ``min_matches``: :class:`TooFewMatchesError`), F by MAGSAC (inliers);
    2. swapped eyes: median inlier ``x_l - x_r`` < 0 in the views' own coordinates -> swap;
    3. already rectified: the matches fitting ``F0`` (|dy| <= 2 x tolerance) are at least
       ``skip_share`` of F's inliers and their |dy| p95 <= ``skip_dy_tolerance`` -> identity
       homographies, ``warp_needed=False`` (mirror images are refused first);
    4. candidates, each computed, none taken for being first: Loop-Zhang on F (not tried when a
       homography explains F's inliers - planar or far scene - or an epipole lies near an
       image), and two row alignments of the right view with the left kept (affine and
       projective in y, fitted to every match with MAD-based outlier rejection, see
       :func:`_row_fit`); mirror / upside-down checks;
    5. per candidate, KeystoneDepth's translation: the right view is shifted along x so that the
       smallest inlier disparity (along-row mismatches left out, see ``disparity_fence``) is 0:
       no inlier disparity is negative and the farthest inlier sits at infinity; the output
       canvas (Loop-Zhang: union of both warped views, at most ``max_canvas_scale`` x the input;
       row alignments: the left view's frame); the distortion and residual-|dy| gates. |dy| p95
       is measured on the same number of matches for every candidate (the most that any one
       puts within ``ALIGNED_GATE`` px of their rows);
    6. the choice (:func:`_choose`): lowest |dy| p95 + ``DISTORTION_COST`` px per degree of shear
       and turn, the simpler model on a tie. A planar or far scene is rectified only by a row
       alignment that turns no view more than ``PLANAR_MAX_TURN`` deg, else refused. With no
       candidate left, the first refusal's type is raised with every candidate's reason.

    Thresholds in px (``skip_dy_tolerance``, ``max_dy_p95``, ``f_threshold``, ``h_threshold``)
    are at the SIFT scale: they grow with the factor by which views over ``max_side`` were
    downscaled for matching (x5 for a 6000 px view), since matches are no more precise than that.
    Raises :class:`InvalidInputError` or a :class:`RectificationError` subclass, nothing else
    (numerical corner cases from OpenCV or LAPACK become a plain ``rectification_failed``).
    """
    clock = time.perf_counter()
    _check_view(left, "the left view")
    _check_view(right, "the right view")
    try:
        return _rectify(left, right, params, principal_point, clock)
    except PipelineError:
        raise
    except (cv2.error, np.linalg.LinAlgError, ValueError, ZeroDivisionError, FloatingPointError) as exc:
        # Safety net for a batch: a numerical corner case is recorded as a typed failure.
        raise RectificationError(f"numerical failure ({type(exc).__name__}): {str(exc).strip()[:160]}") from exc


def _rectify(
    left: np.ndarray, right: np.ndarray, params: RectifyParams, principal_point: tuple[float, float] | None, clock: float
) -> Rectification:
    pts_l, pts_r = match_features(left, right, params)
    sift_scale = max(1.0, max(max(left.shape[:2]), max(right.shape[:2])) / params.max_side)
    return _rectify_matches(pts_l, pts_r, left.shape[:2][::-1], right.shape[:2][::-1], params, principal_point, clock, sift_scale)


def rectify_matches(
    pts_l: np.ndarray,
    pts_r: np.ndarray,
    left_size: tuple[int, int],
    right_size: tuple[int, int],
    params: RectifyParams = RectifyParams(),
    principal_point: tuple[float, float] | None = None,
    match_scale: float = 1.0,
) -> Rectification:
    """:func:`rectify_pair` from given matches: ``pts_l``, ``pts_r`` ``(N, 2)`` px in views of
    ``left_size`` / ``right_size`` ``(width, height)`` px. ``match_scale``: px per matching px
    (> 0: under 1 when small views were matched upsampled, as the filter does; the thresholds in
    ``params`` are at the matching scale, and never under one view pixel). Same decisions, same
    errors."""
    pts_l, pts_r = (np.asarray(p, np.float64) for p in (pts_l, pts_r))
    if pts_l.ndim != 2 or pts_l.shape[1:] != (2,) or pts_l.shape != pts_r.shape:
        raise InvalidInputError(f"Expected two (N, 2) point arrays, got {pts_l.shape} and {pts_r.shape}")
    if not (np.all(np.isfinite(pts_l)) and np.all(np.isfinite(pts_r))):
        raise InvalidInputError("Expected finite match coordinates, got NaN or inf")
    sizes = [tuple(int(v) for v in size) for size in (left_size, right_size)]
    if any(len(size) != 2 or min(size) < MIN_SIDE for size in sizes):
        raise InvalidInputError(f"Expected view sizes (width, height) of at least {MIN_SIDE} px, got {sizes}")
    left_wh, right_wh = ((size[0], size[1]) for size in sizes)  # both (width, height), checked above
    if not (math.isfinite(match_scale) and match_scale > 0.0):
        raise InvalidInputError(f"Expected match_scale > 0, got {match_scale}")
    try:
        # A threshold is never finer than a pixel of the views themselves: matches found on a small
        # scan's halves upsampled to the filter's side are no more precise than the scan's pixels
        # (thresholds at 0.38 px moved a 460 px card's rectification 5 deg under a 16 px crop).
        threshold_scale = max(1.0, match_scale)
        return _rectify_matches(pts_l, pts_r, left_wh, right_wh, params, principal_point, time.perf_counter(), threshold_scale)
    except PipelineError:
        raise
    except (cv2.error, np.linalg.LinAlgError, ValueError, ZeroDivisionError, FloatingPointError) as exc:
        raise RectificationError(f"numerical failure ({type(exc).__name__}): {str(exc).strip()[:160]}") from exc


def _rectify_matches(
    pts_l: np.ndarray,
    pts_r: np.ndarray,
    left_size: tuple[int, int],
    right_size: tuple[int, int],
    params: RectifyParams,
    principal_point: tuple[float, float] | None,
    clock: float,
    sift_scale: float,
) -> Rectification:
    n = len(pts_l)
    if n < params.min_matches:
        raise TooFewMatchesError(f"{n} matches < {params.min_matches}")
    # The pair decides what it is before F is trusted: with enough matches and no F (OpenCV's
    # USAC finds no model when the matches fix no epipolar geometry: a pure shift of a textured
    # pair, a planar or far scene), the already-aligned test and the row alignments still run on
    # every match, as for a planar scene; only when those fail too is the pair refused, saying so.
    no_f: PlanarSceneError | None = None
    try:
        F, mask = _fit_f(pts_l, pts_r, params, sift_scale)
    except TooFewMatchesError as exc:
        no_f = PlanarSceneError(f"{exc} from {n} matches: they fix no epipolar geometry (planar, far or purely shifted)")
        F, mask = np.zeros((3, 3)), np.ones(n, bool)
    n_f = int(mask.sum())
    if n_f < params.min_inliers:
        raise TooFewMatchesError(f"{n_f} fundamental-matrix inliers < {params.min_inliers} (of {n} matches)")

    sizes = [left_size, right_size]
    il, ir = pts_l[mask], pts_r[mask]
    swapped = False
    if params.detect_swapped and float(np.median(il[:, 0] - ir[:, 0])) < 0:
        swapped = True
        sizes = [right_size, left_size]
        pts_l, pts_r, il, ir = pts_r, pts_l, ir, il
        F = F.T.copy()
    (wl, hl), (wr, hr) = sizes[0], sizes[1]

    # Already rectified within tolerance?
    tol = params.skip_dy_tolerance * sift_scale
    fit0 = _f0_inliers(pts_l, pts_r, 2.0 * tol) & (mask if mask.sum() >= params.min_inliers else True)
    if int(fit0.sum()) >= max(params.min_inliers, params.skip_share * n_f):
        dy0 = np.abs(pts_l[fit0, 1] - pts_r[fit0, 1])
        if float(np.percentile(dy0, 95)) <= tol:
            _check_not_mirrored(pts_l[fit0, 0], pts_r[fit0, 0])
            d0 = pts_l[fit0, 0] - pts_r[fit0, 0]
            d0 = d0[_disparity_keep(d0, max(wl, wr), params.disparity_fence)]
            size = (max(wl, wr), max(hl, hr))
            reason = (
                f"already rectified within tolerance: |dy| p95 {np.percentile(dy0, 95):.2f} px "
                f"<= {tol:.2f} px over {int(fit0.sum())} of {n} matches"
            )
            # Halves cropped with different margins carry a horizontal offset that can make
            # disparities negative; the paper's rule (no negative disparity) then needs a
            # translation of the right view, x_r' = x_r + d_min, which is still a warp.
            d_min, d_max = float(d0.min()), float(d0.max())
            H_r = np.eye(3)
            if d_min < 0:
                H_r[0, 2] = d_min
                reason += f"; right view translated {d_min:.1f} px so that no disparity is negative"
                d_min, d_max = 0.0, d_max - d_min
            return Rectification(
                H_l=np.eye(3),
                H_r=H_r,
                size=size,
                K=_intrinsics(size, principal_point, np.eye(3)),
                R=np.eye(3),
                t=np.array([-1.0, 0.0, 0.0]),
                disparity_range=(d_min, d_max),
                dy_median=float(np.median(dy0)),
                dy_p95=float(np.percentile(dy0, 95)),
                midline_angle=90.0,
                aspect_change=1.0,
                shear=0.0,
                kept_fraction=1.0,
                matches=n,
                inliers=int(fit0.sum()),
                swapped=swapped,
                warp_needed=bool(H_r[0, 2] != 0),
                reason=reason,
                method="identity",
                seconds=time.perf_counter() - clock,
                F=F,
                inlier_points=(pts_l[fit0], pts_r[fit0]),
            )

    n_h = _homography_inliers(pts_l, pts_r, params, sift_scale) if no_f is None else 0
    planar = no_f
    if no_f is None and n_h >= params.planar_ratio * n_f:
        # F is degenerate and its epipole arbitrary: Loop-Zhang is not tried. A far scene of a
        # nearly rectified pair still has well-defined rows, so the row alignments may rectify it
        # if they turn no view more than PLANAR_MAX_TURN; else the pair is refused.
        planar = PlanarSceneError(
            f"a homography explains {n_h} matches vs {n_f} for F (>= {params.planar_ratio:.0%}): "
            "planar or far scene, the epipole is undetermined"
        )

    # Candidates: Loop-Zhang from F, and the row alignments (left view kept) fitted robustly to
    # every match. All are scored on the same matches; the choice is made by measurement
    # (see _choose), not by which one failed first.
    refused: list[RectificationError] = []
    proposals: list[tuple[str, np.ndarray, np.ndarray]] = []
    near = []
    if no_f is None:
        e_l, e_r = epipoles(F)
        near = [
            name
            for name, e, (w_, h_) in (("left", e_l, (wl, hl)), ("right", e_r, (wr, hr)))
            if _epipole_near(e, w_, h_, params.epipole_margin)
        ]
    if planar is not None:
        refused.append(planar)
    elif near:
        # Near-planar content gives an F whose epipole lands anywhere: Loop-Zhang is not tried.
        refused.append(
            EpipoleInImageError(f"the {near[0]} epipole lies within {params.epipole_margin} half-diagonals of the centre")
        )
    else:
        try:
            H_l, H_r = loop_zhang(F, wl, hl, wr, hr)
            proposals.append(("loop_zhang", H_l, H_r))
        except (DistortionError, EpipoleInImageError, UnboundedWarpError) as exc:
            refused.append(exc)
    for model in ROW_MODELS:
        H_r_row = _row_fit(pts_l, pts_r, model, (wr, hr), params, sift_scale)
        if H_r_row is None:
            refused.append(ResidualDyError(f"row_{model}: no robust fit of the rows"))
        else:
            proposals.append((f"row_{model}", np.eye(3), H_r_row))

    gate = ALIGNED_GATE * sift_scale
    dys = {}
    for name, H_l, H_r in proposals:
        dy, _ = _dy_stats(H_l, H_r, pts_l, pts_r)
        dys[name] = np.where(np.isfinite(dy), np.abs(dy), np.inf)
    n_good = max((int(np.sum(d <= gate)) for d in dys.values()), default=0)
    done: list[Rectification] = []
    for name, H_l, H_r in proposals:
        try:
            done.append(
                _finish(name, H_l, H_r, pts_l, pts_r, dys[name], n_good, (wl, hl), (wr, hr), params, sift_scale, principal_point)
            )
        except (DistortionError, UnboundedWarpError, ResidualDyError) as exc:
            refused.append(exc)
    if planar is not None:
        done = [r for r in done if r.rotation <= PLANAR_MAX_TURN]
        if not done:
            raise planar
    if not done:
        first = next((e for e in refused if not isinstance(e, ResidualDyError)), refused[0] if refused else None)
        kind = type(first) if first is not None else ResidualDyError
        raise kind("; ".join(str(e) for e in refused) or "no rectification candidate")
    chosen = _choose(done, sift_scale)
    others = "; ".join(
        f"{r.method} |dy| p95 {r.dy_p95:.2f} px, distortion {_distortion(r):.1f} deg" for r in done if r is not chosen
    )
    reason = chosen.reason + (f" (chosen over {others})" if others else "")
    if planar is not None:
        reason += " (far or planar scene: F undetermined, rows aligned without it)"
    elif near:
        reason += f" (F put the {near[0]} epipole inside the image)"
    return replace(
        chosen,
        matches=n,
        inliers=n_f if chosen.method == "loop_zhang" else chosen.inliers,
        swapped=swapped,
        F=F,
        reason=reason,
        seconds=time.perf_counter() - clock,
    )


ROW_MODELS = ("affine", "projective")
"""Row alignments of the right view, the left kept: ``affine`` ``y' = a x + b y + c`` with
``x' = b x - a y + t`` (a similarity: no shear); ``projective`` the same numerators over
``g x + h y + 1``."""
ALIGNED_GATE = 3.0
"""px at the SIFT scale: a match further than this from its row after rectification is a gross
or near-miss mismatch, not residual; the candidates are scored on the same number of matches."""
SIMPLICITY = {"row_affine": 0, "row_projective": 1, "loop_zhang": 2}
DISTORTION_COST = 0.15
"""px (at the SIFT scale) of |dy| p95 that one degree of distortion (``_distortion``) must buy.
Loop-Zhang turns both views of a nearly rectified pair by the loose direction of F's epipole
(2-6 deg on real cards, changing with a crop of a few px) for a few tenths of a px of |dy|."""
COST_TIE = 0.1  # px at the SIFT scale: costs this close are equal, and the simpler model wins
PLANAR_MAX_TURN = 1.0
"""deg: a far or planar scene (F degenerate) is row-aligned only if no view is turned further."""


def _distortion(rect: Rectification) -> float:
    """deg: ``|midline angle - 90| + |rotation|`` of the worse view (shear plus turn)."""
    return abs(rect.midline_angle - 90.0) + abs(rect.rotation)


def _cost(rect: Rectification, sift_scale: float) -> float:
    """px at the SIFT scale: ``dy_p95 / sift_scale + DISTORTION_COST x distortion``."""
    return rect.dy_p95 / sift_scale + DISTORTION_COST * _distortion(rect)


def _choose(done: list[Rectification], sift_scale: float) -> Rectification:
    """The rule: the lowest :func:`_cost` (measured |dy| p95 plus ``DISTORTION_COST`` px per deg
    of shear and turn) wins; among candidates within ``COST_TIE`` px of it, the simplest model
    (row affine < row projective < Loop-Zhang). A nearly rectified pair thus keeps its left view
    as it is, and a keystoned pair, whose rows no row alignment can match, gets Loop-Zhang."""
    best = min(_cost(r, sift_scale) for r in done)
    level = [r for r in done if _cost(r, sift_scale) <= best + COST_TIE]
    return min(level, key=lambda r: (SIMPLICITY[r.method], _cost(r, sift_scale)))


def _row_fit(
    pts_l: np.ndarray,
    pts_r: np.ndarray,
    model: str,
    right_size: tuple[int, int],
    params: RectifyParams,
    sift_scale: float,
) -> np.ndarray | None:
    """Robust row alignment of the right view onto the left: ``H_r`` or None.

    Outliers: the start keeps matches within 3 robust sigmas (1.4826 MAD, at least 3 px at the
    SIFT scale) of the median row offset, so that a few gross matches (|dy| of hundreds of px)
    cannot pull the fit; then least squares on the kept matches, the residuals' robust sigma,
    keep within 3 sigmas (at least 1 px at the SIFT scale), refit, until the kept set is stable
    (at most 10 rounds). The projective model starts from the affine fit's kept set and is linear
    in ``(a, b, c, g, h)`` (``y_l (g x + h y + 1) = a x + b y + c``). None when fewer than
    ``min_inliers`` remain, the fit is not finite, the row scale changes by more than
    ``max_row_scale_change`` (a zoom) or the projective denominator is not positive over the view.
    """
    if len(pts_l) < params.min_inliers:
        return None
    yl, x, y = pts_l[:, 1], pts_r[:, 0], pts_r[:, 1]
    offset = yl - y
    med = float(np.median(offset))
    keep = np.abs(offset - med) <= max(3.0 * 1.4826 * float(np.median(np.abs(offset - med))), 3.0 * sift_scale)
    if model == "projective":
        start = _row_fit(pts_l, pts_r, "affine", right_size, params, sift_scale)
        if start is None:
            return None
        keep = np.abs(yl - (start[1, 0] * x + start[1, 1] * y + start[1, 2])) <= ALIGNED_GATE * sift_scale
    coef = np.zeros(5)
    for _ in range(10):
        if int(keep.sum()) < params.min_inliers:
            return None
        xs, ys, yls = x[keep], y[keep], yl[keep]
        if model == "affine":
            design = np.column_stack([xs, ys, np.ones(len(xs))])
        else:
            design = np.column_stack([xs, ys, np.ones(len(xs)), -xs * yls, -ys * yls])
        # Columns in px are badly scaled against the constant: solve in scaled units.
        norms = np.linalg.norm(design, axis=0)
        norms[norms == 0] = 1.0
        sol, *_ = np.linalg.lstsq(design / norms, yls, rcond=None)
        coef[: len(sol)] = sol / norms
        if not np.all(np.isfinite(coef)):
            return None
        den = coef[3] * x + coef[4] * y + 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            resid = yl - (coef[0] * x + coef[1] * y + coef[2]) / den
        resid = np.where(np.isfinite(resid), resid, np.inf)
        sigma = 1.4826 * float(np.median(np.abs(resid[keep] - np.median(resid[keep]))))
        new = np.abs(resid) <= max(3.0 * sigma, 1.0 * sift_scale)
        if np.array_equal(new, keep):
            break
        keep = new
    if int(keep.sum()) < params.min_inliers:
        return None
    a, b, c, g, h = coef
    wr, hr = right_size
    corners = np.array([[0, 0], [wr - 1, 0], [wr - 1, hr - 1], [0, hr - 1]], np.float64)
    if model == "projective" and not np.all(g * corners[:, 0] + h * corners[:, 1] + 1.0 > 0.5):
        return None
    den_centre = g * (wr - 1) / 2.0 + h * (hr - 1) / 2.0 + 1.0
    if abs(b / den_centre - 1.0) > params.max_row_scale_change:
        return None  # a zoom between the views, not a nearly rectified pair
    # x' = b x - a y: the right view is turned (and scaled) as a whole, as a camera rolled by
    # asin(a) would be, rather than sheared; y' (the row fit) is unchanged by it.
    return np.array([[b, -a, 0.0], [a, b, c], [g, h, 1.0]])


def _finish(
    method: str,
    H_l: np.ndarray,
    H_r: np.ndarray,
    pts_l: np.ndarray,
    pts_r: np.ndarray,
    abs_dy: np.ndarray,
    n_good: int,
    left_size: tuple[int, int],
    right_size: tuple[int, int],
    params: RectifyParams,
    sift_scale: float,
    principal_point: tuple[float, float] | None,
) -> Rectification:
    """KeystoneDepth's translation, the output canvas, the distortion and residual gates for one
    candidate. ``abs_dy``: |dy| of every match under the candidate (px); its score ``dy_p95`` is
    the p95 over the ``n_good`` best-aligned matches (the most any candidate aligns within
    ``ALIGNED_GATE``), so that candidates are compared on equal numbers of matches."""
    (wl, hl), (wr, hr) = left_size, right_size
    aligned = abs_dy <= ALIGNED_GATE * sift_scale
    if int(aligned.sum()) < params.min_inliers or n_good < params.min_inliers:
        raise ResidualDyError(f"{method}: only {int(aligned.sum())} matches on their rows")
    il, ir = pts_l[aligned], pts_r[aligned]
    dy, disp = _dy_stats(H_l, H_r, il, ir)
    if not (np.all(np.isfinite(dy)) and np.all(np.isfinite(disp))):
        raise UnboundedWarpError(f"{method}: an inlier maps to infinity")
    _check_not_mirrored(_apply(H_l, il)[:, 0], _apply(H_r, ir)[:, 0])
    best = np.sort(abs_dy)[:n_good]
    dy_med, dy_p95 = float(np.median(best)), float(np.percentile(best, 95))
    if not np.isfinite(dy_p95):
        raise UnboundedWarpError(f"{method}: a match maps to infinity")

    # KeystoneDepth: translate after rectification so that no inlier disparity is negative; the
    # smallest (row mismatches left out) becomes 0, i.e. the farthest inlier is put at infinity.
    keep = _disparity_keep(disp, max(wl, wr), params.disparity_fence)
    shift = float(disp[keep].min())
    disp = disp - shift
    H_r = np.array([[1, 0, shift], [0, 1, 0], [0, 0, 1.0]]) @ H_r

    if method == "loop_zhang":
        # Output canvas: union of both warped views, bounded by max_canvas_scale x the input size.
        quads = [_quad(H_l, wl, hl), _quad(H_r, wr, hr)]
        if not all(np.all(np.isfinite(qd)) for qd in quads):
            raise UnboundedWarpError(f"{method}: a corner of a view maps to infinity")
        allq = np.vstack(quads)
        lo, hi = allq.min(axis=0), allq.max(axis=0)
        cap = params.max_canvas_scale * np.array([max(wl, wr), max(hl, hr)], np.float64)
        span = np.minimum(hi - lo, cap)
        lo = (lo + hi) / 2 - span / 2
        size = (max(1, math.ceil(span[0])), max(1, math.ceil(span[1])))
        if size[0] * size[1] > params.max_output_pixels:
            raise UnboundedWarpError(f"output {size[0]}x{size[1]} exceeds {params.max_output_pixels:,} pixels")
        move = np.array([[1, 0, -lo[0] - 0.5], [0, 1, -lo[1] - 0.5], [0, 0, 1.0]])
        H_l, H_r = move @ H_l, move @ H_r
    else:
        size = (max(wl, wr), max(hl, hr))  # the left view stays where it is
    canvas = np.array([[-0.5, -0.5], [size[0] - 0.5, -0.5], [size[0] - 0.5, size[1] - 0.5], [-0.5, size[1] - 0.5]], np.float32)
    kept = 1.0
    for H, (w_, h_) in ((H_l, (wl, hl)), (H_r, (wr, hr))):
        qd = _quad(H, w_, h_)
        if not np.all(np.isfinite(qd)):
            raise UnboundedWarpError(f"{method}: a corner of a view maps to infinity")
        qd = qd.astype(np.float32)
        area = abs(cv2.contourArea(qd))
        inter, _ = cv2.intersectConvexConvex(qd, canvas)
        kept = min(kept, float(inter) / area if area > 0 else 0.0)

    ml, mr = distortion_metrics(H_l, wl, hl), distortion_metrics(H_r, wr, hr)
    worst = ml if abs(ml["midline_angle"] - 90) >= abs(mr["midline_angle"] - 90) else mr
    aspect = max(ml["aspect_change"], mr["aspect_change"])
    shear = max(ml["shear"], mr["shear"])
    rotation = max(abs(ml["rotation"]), abs(mr["rotation"]))
    if abs(worst["midline_angle"] - 90) > params.max_midline_deviation:
        raise DistortionError(
            f"{method}: midline angle {worst['midline_angle']:.1f} deg, limit 90 +- {params.max_midline_deviation}"
        )
    if aspect > params.max_aspect_change:
        raise DistortionError(f"{method}: aspect change {aspect:.2f} > {params.max_aspect_change}")
    if rotation > params.max_rotation:
        # Stereo cameras of the period were levelled: a view turned further is the symptom of a
        # wrong F (a nearly rectified or near-planar pair leaves the epipole direction loose).
        raise DistortionError(f"{method}: a view is rotated {rotation:.1f} deg, limit {params.max_rotation}")
    if kept < params.min_kept_fraction:
        raise DistortionError(f"{method}: only {kept:.0%} of a view fits the bounded canvas (< {params.min_kept_fraction:.0%})")
    if dy_p95 > params.max_dy_p95 * sift_scale:
        raise ResidualDyError(f"{method}: |dy| p95 {dy_p95:.2f} px > {params.max_dy_p95 * sift_scale:.2f} px")
    label = {
        "loop_zhang": "rectified (Loop-Zhang)",
        "row_affine": "row-aligned (nearly rectified pair)",
        "row_projective": "row-aligned with a projective term (nearly rectified pair)",
    }[method]
    return Rectification(
        H_l=H_l,
        H_r=H_r,
        size=size,
        K=_intrinsics(size, principal_point, H_l),
        R=np.eye(3),
        t=np.array([-1.0, 0.0, 0.0]),
        disparity_range=(float(disp[keep].min()), float(disp[keep].max())),
        dy_median=dy_med,
        dy_p95=dy_p95,
        midline_angle=float(worst["midline_angle"]),
        aspect_change=float(aspect),
        rotation=float(rotation),
        shear=float(shear),
        kept_fraction=float(kept),
        matches=len(pts_l),
        inliers=int(aligned.sum()),
        swapped=False,
        warp_needed=True,
        reason=f"{label}: |dy| p95 {dy_p95:.2f} px, midline angle {worst['midline_angle']:.1f} deg",
        inlier_points=(il, ir),
        method=method,
    )


def implied_pose(H_l: np.ndarray, H_r: np.ndarray, K: np.ndarray) -> dict[str, Any]:
    """The original cameras' relative pose implied by the rectification (an approximation).

    With both original cameras taken to share ``K`` (the paper's 45 deg field of view), a
    rectifying homography is ``H ~ K R K^-1`` for the rotation ``R`` that turns a camera into the
    rectified frame. Loop-Zhang adds a shear and scale, so each ``R`` is the rotation nearest to
    ``K^-1 H K`` (polar decomposition by SVD, det +1). The rectified cameras are ``[I | 0]`` and
    ``[I | (-1, 0, 0)]`` (unit baseline along x), so the original right camera sees
    ``X_r = R X_l + t`` with ``R = R_r^T R_l`` and ``t = R_r^T (-1, 0, 0)``.
    """
    K_inv = np.linalg.inv(K)

    def nearest_rotation(M: np.ndarray) -> np.ndarray:
        U, _, Vt = np.linalg.svd(M / np.cbrt(np.linalg.det(M)) if np.linalg.det(M) != 0 else M)
        R = U @ Vt
        if np.linalg.det(R) < 0:
            U[:, -1] *= -1
            R = U @ Vt
        return R

    R_l = nearest_rotation(K_inv @ H_l @ K)
    R_r = nearest_rotation(K_inv @ H_r @ K)
    R = R_r.T @ R_l
    t = R_r.T @ np.array([-1.0, 0.0, 0.0])
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return {"R_left": R_l.tolist(), "R_right": R_r.tolist(), "R": R.tolist(), "t": t.tolist(), "relative_rotation_deg": angle}


def _intrinsics(size: tuple[int, int], principal_point: tuple[float, float] | None, H_l: np.ndarray) -> np.ndarray:
    """Shared ``K``: ``f = 1.2071 x output height`` (45 deg vertical FOV); principal point the
    full image's centre mapped through ``H_l`` where known, else the output centre (px)."""
    width, height = size
    f = FOCAL_PER_HEIGHT * height
    if principal_point is not None and np.all(np.isfinite(principal_point)):
        cx, cy = _apply(H_l, np.array([principal_point], np.float64))[0]
        if not (np.isfinite(cx) and np.isfinite(cy)):
            cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    else:
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def warp_pair(left: np.ndarray, right: np.ndarray, rect: Rectification) -> tuple[np.ndarray, np.ndarray]:
    """Rectified views ``(left_rect, right_rect)``, each ``rect.size`` (w, h), same dtype/channels.

    ``left``/``right`` are the views as given to :func:`rectify_pair`; they are swapped first if
    ``rect.swapped``. Without ``warp_needed`` the (swapped) views come back padded to the common
    size. Bilinear interpolation, black outside. With ``rect.view_scale < 1`` each input is first
    downscaled by about that factor with an area filter (bilinear sampling alone would alias a
    3x reduction) and warped by ``H S_in^-1`` (``S_in``: :func:`scaling_matrix` of the resize
    actually done), which is the same geometry as ``H`` on the full-resolution input. Raises
    :class:`UnboundedWarpError` for non-finite homographies or a canvas over 8x the inputs'
    larger side.
    """
    _check_view(left, "the left view")
    _check_view(right, "the right view")
    if rect.swapped:
        left, right = right, left
    width, height = rect.size
    limit = 8 * max(left.shape[0], left.shape[1], right.shape[0], right.shape[1])
    if not (0 < width <= limit and 0 < height <= limit):
        raise UnboundedWarpError(f"output {width}x{height} beyond 8x the input size")
    if not (np.all(np.isfinite(rect.H_l)) and np.all(np.isfinite(rect.H_r))):
        raise UnboundedWarpError("non-finite homography")
    out = []
    for image, H in ((left, rect.H_l), (right, rect.H_r)):
        image = np.ascontiguousarray(image)
        if rect.view_scale < 1.0:
            h_in, w_in = image.shape[:2]
            small = (max(1, round(w_in * rect.view_scale)), max(1, round(h_in * rect.view_scale)))
            if small != (w_in, h_in):
                image = cv2.resize(image, small, interpolation=cv2.INTER_AREA)
                H = H @ np.linalg.inv(scaling_matrix(small[0] / w_in, small[1] / h_in))
        warped = cv2.warpPerspective(
            image,
            H,
            (width, height),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        out.append(warped)
    return out[0], out[1]


def photograph_mask(view: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: the pixels of a rectified view ``(H, W)`` or ``(H, W, C)`` that are not the
    warp's black fill (:func:`warp_pair` fills outside with 0): any channel above 0.

    One OR over the channels' strided planes: a ``max`` along the last, 3-long axis of an 800 px
    RGB view took 15 ms (numpy reduces a short inner axis slowly), this takes ~1 ms."""
    if view.ndim == 2:
        return view > 0
    merged = view[..., 0].copy()
    for channel in range(1, view.shape[2]):
        merged |= view[..., channel]
    return merged > 0


# ------------------------------------------------------------------------- working resolution


def scaling_matrix(sx: float, sy: float | None = None) -> np.ndarray:
    """3x3 ``S`` taking px of an image to px of the same image resized by ``(sx, sy)``.

    With the origin at the top-left pixel *centre* (module conventions), the pixel edge is at
    -0.5, so ``x' + 0.5 = sx (x + 0.5)``: ``S = [[sx, 0, (sx-1)/2], [0, sy, (sy-1)/2], [0, 0, 1]]``.
    A homography ``H`` between full-resolution images becomes ``S_out H S_in^-1`` between resized
    ones, and back: ``H_full = S_out^-1 H_work S_in``.
    """
    sy = sx if sy is None else sy
    if not (math.isfinite(sx) and math.isfinite(sy) and sx > 0 and sy > 0):
        raise InvalidInputError(f"Expected finite scales > 0, got {sx}, {sy}")
    return np.array([[sx, 0.0, (sx - 1.0) / 2.0], [0.0, sy, (sy - 1.0) / 2.0], [0.0, 0.0, 1.0]])


def stored_view_scale(size: tuple[int, int], work_side: int | None) -> float:
    """Scale (<= 1) that brings a ``size = (width, height)`` px view to at most ``work_side`` px
    on its longer side; 1 when it already fits or ``work_side`` is None (full resolution)."""
    width, height = (int(v) for v in size)
    if width < 1 or height < 1:
        raise InvalidInputError(f"Expected a view size of at least 1 x 1 px, got {size}")
    if work_side is None:
        return 1.0
    if work_side < 1:
        raise InvalidInputError(f"Expected work_side >= 1 px or None, got {work_side}")
    return min(1.0, work_side / max(width, height))


def scale_rectification(rect: Rectification, scale: float) -> Rectification:
    """The same rectification with its output frame resized by ``scale`` (0 < scale <= 1).

    The inputs stay the full-resolution views; what describes the output changes with it:
    ``H' = S H`` (:func:`scaling_matrix`), ``size' = round(size x scale)``, ``K' = S K``
    (focal length times ``scale``, principal point moved with the pixel centres), the disparity
    range and |dy| times ``scale`` (px of the scaled views). Angles, aspect change, shear, kept
    fraction, F and the inlier matches (input px) do not change. ``view_scale`` multiplies.
    """
    if not (math.isfinite(scale) and 0.0 < scale <= 1.0):
        raise InvalidInputError(f"Expected 0 < scale <= 1, got {scale}")
    if scale == 1.0:
        return rect
    width, height = rect.size
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    S = scaling_matrix(size[0] / width, size[1] / height)
    s = math.sqrt(S[0, 0] * S[1, 1])  # the two differ by the rounding of the size only
    return replace(
        rect,
        H_l=S @ rect.H_l,
        H_r=S @ rect.H_r,
        size=size,
        K=S @ rect.K,
        disparity_range=(rect.disparity_range[0] * S[0, 0], rect.disparity_range[1] * S[0, 0]),
        dy_median=rect.dy_median * S[1, 1],
        dy_p95=rect.dy_p95 * S[1, 1],
        view_scale=rect.view_scale * s,
    )
