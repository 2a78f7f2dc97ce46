"""View synthesis geometry (KeystoneDepth, Luo et al.; docs/PIPELINE.md): GD images, the quad of corner
cameras, textured-mesh reprojection with holes, and double-reprojection training holes.

Pure numpy/scipy; no torch, no web or database imports.

Conventions
-----------
* A **GD image** is a grey intensity ``I`` (H, W) (or a colour one, (H, W, 3) RGB) float32 in [0, 1] and a depth ``D`` (H, W)
  float32 (> 0 where ``valid``; depth up to scale, in the stereo baseline's units, ``D = f b / d``
  as in :func:`pipeline.disparity.depth_from_disparity`), with a focal length ``f`` in pixels.
* Pixels: ``(u, v)`` = (column, row); pixel centres lie at integer coordinates; the principal point
  is the image centre ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``.
* Cameras follow the paper's (OpenGL) convention: camera frame x right, y up, the camera **looks
  down -z**. A pixel ``(u, v)`` with depth ``D`` unprojects to
  ``X = (u - cx) D / f``, ``Y = -(v - cy) D / f``, ``Z = -D``; depth is ``D = -Z`` (> 0 in front).
* The world frame is the reference camera v0's frame (v0 = identity pose at the origin).
  A :class:`Camera` maps world to camera coordinates, ``x_cam = R x_world + t``.
* Scene centre ``c = (0, 0, -1 / median(1 / D0))`` over v0's valid pixels (in front of v0, on -z).
* Corner cameras v1..v4 sit at ``(+-r_w, +-r_h, 0)`` and look at ``c`` with v0's up vector
  ``(0, 1, 0)``; ``r_w = r_h = 96 b / d_max * sqrt(2) / 2``, where ``d_max = f b / min(D0)`` is the
  largest disparity in px (the nearest valid point). So ``r_w = 96 min(D0) / f * sqrt(2) / 2``: the
  baseline cancels, and the nearest point moves about 96 px (at the paper's 512 x 512) between v0
  and a corner. ``shift_px`` overrides the 96 for other resolutions.

Reprojection (:func:`reproject`)
--------------------------------
The source GD image becomes a triangle mesh over its pixel grid (2 triangles per 2 x 2 pixel quad,
vertices at pixel centres). A triangle is **dropped** when a vertex is invalid, lies behind the
target camera, or at a depth discontinuity: its vertices' source depths differ in relative depth by
more than 0.1, ``max_ij |D_i - D_j| / min(D_i, D_j) > 0.1`` (the paper's rule), and, when
``max_stretch_px`` is given, the triangle also stretches: its vertices move apart by more than
that many pixels between the two cameras, ``f_s |C_t - C_s| (1 / D_min - 1 / D_max)``, with the
depths read through a 3 x 3 median (a lone noisy pixel is no edge). Without the stretch test a far
surface (disparity of a pixel or less, where flow noise makes 10 % steps) or a slanted plane breaks
into cracks. The kept triangles are rasterised **exactly** (every target pixel centre inside a
projected triangle) with a z-buffer (nearest wins), vectorised in numpy: the per-triangle work runs
on slices of the (H-1, W-1) grid of pixel quads, where each triangle first tests the one pixel
centre at its bounding box's corner with no gather (72 % of the triangles of a 512 px corner view
have no other); the triangles whose box holds up to 3 x 3 centres (98 % of the rest) test their
other centres in one pass over their gathered columns, the few larger ones through a repeat. The
depth-edge half of the rule depends on the target only through its distance from the source
(:class:`ContinuousTriangles`): the four corner cameras, at one distance, share one. Shading
gathers and scatters one flat plane per channel (a third of the cost of (N, 3) rows).
Fragments are float32 (positions to 3e-5 px): the renders match the float64 rasteriser before it
to 4e-6 in intensity and 2e-6 in relative depth (``keystone bench views``). Within a triangle the
inverse depth is interpolated linearly in screen space (exact for a planar triangle) and the
intensity perspective-correctly. Target pixels no kept triangle covers are **holes** (this includes
regions outside the source's field of view). No anti-aliasing: intensities are sampled at pixel
centres, so resampling blurs like bilinear interpolation. The mesh ends at the source's border
pixel centres, so a target pixel whose centre falls just outside that footprint is a hole (a round
trip v0 -> v' -> v0 loses up to one pixel along v0's border on the sides v' does not see).
Cost: ~0.05 CPU-s for a 512 x 503 colour view with its boundary mask (0.085-0.095 s for the
code before the grid pass, bit-identical output; 0.13-0.25 s for the float64 rasteriser before
that) on one core of the shared 2-core machine.

Boundary mask (:func:`boundary_mask`)
-------------------------------------
``B`` = the non-hole, valid 8-neighbours of each hole (connected component) that are on its
**foreground** side: a component whose border pixels span a depth step (farthest / nearest border
depth > 1.1, the same 0.1 rule) marks its border pixels nearer than the midpoint in inverse depth,
``1/D > (1/D_near + 1/D_far) / 2``. A hole with no depth step around it (e.g. out of the field of
view) has no foreground side and contributes nothing to ``B``. Approximation: one split per
component; a hole bordered by several depth layers is split at one midpoint.

Double reprojection (:func:`double_reprojection`, :func:`training_holes`)
-------------------------------------------------------------------------
v0 -> v' (a corner camera) -> v0: the second pass uses v' as a GD image whose valid pixels are the
ones the first pass covered, so triangles touching v' holes are dropped and the holes that come
back in v0's frame are shaped like real disocclusions (on the side opposite to v''s motion). The
boundary mask there uses v0's own depth. Training needs no second view. The holes include the
parts of v0 that leave v''s field of view (they have no foreground side, so no ``B``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from .errors import InvalidInputError

__all__ = [
    "MAX_RELATIVE_DEPTH_STEP",
    "MIN_SIDE",
    "SHIFT_PX",
    "Camera",
    "ContinuousTriangles",
    "GDImage",
    "NoValidDepthError",
    "Reprojection",
    "ViewImageTooSmallError",
    "boundary_mask",
    "continuous_triangles",
    "corner_cameras",
    "corner_views",
    "double_reprojection",
    "crack_fraction",
    "look_at",
    "make_gd_image",
    "max_disparity",
    "needs_inpainting",
    "quad_radius",
    "reference_camera",
    "reproject",
    "scene_centre",
    "training_holes",
]

MAX_RELATIVE_DEPTH_STEP = 0.1  # the paper's triangle-dropping threshold
SHIFT_PX = 96.0  # the paper's quad size: the nearest point moves ~96 px (at 512 x 512)
MIN_SIDE = 2  # a mesh needs at least one 2 x 2 pixel quad
MOSTLY_HOLES = 0.5  # a view with more holes than this is reported as mostly holes
_DEPTH_RANGE = 1e6  # depths below median/1e6 or above median*1e6 count as zero / infinite
_CHUNK = 2_000_000  # candidate pixels rasterised at once (memory bound)
_SMALL_BOX = 3  # triangles whose box holds at most this many centres a side: one pass per offset
_SMALL_BOX_OFFSETS = [(i, j) for j in range(_SMALL_BOX) for i in range(_SMALL_BOX) if i or j]


class NoValidDepthError(InvalidInputError):
    """Nothing in the GD image has a usable (finite, positive, non-degenerate) depth."""

    code = "no_valid_depth"


class ViewImageTooSmallError(InvalidInputError):
    """The image has no 2 x 2 pixel quad to build a mesh from."""

    code = "image_too_small"


# ------------------------------------------------------------------------------------ data types
@dataclass(frozen=True)
class GDImage:
    """A grey (or colour) + depth image. ``intensity`` (H, W) grey or (H, W, 3) RGB, float32 in [0, 1]; ``depth`` (H, W) float32,
    > 0 and finite where ``valid`` (H, W) bool, 0 elsewhere; ``focal_px`` the focal length in px.
    Build it with :func:`make_gd_image` (which validates and masks)."""

    intensity: np.ndarray
    depth: np.ndarray
    valid: np.ndarray
    focal_px: float

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.depth.shape[0]), int(self.depth.shape[1]))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking down its -z axis. ``rotation`` (3, 3) and ``translation`` (3,)
    map world to camera coordinates, ``x_cam = R x_world + t``; ``focal_px`` in px; the principal
    point is the image centre of a ``width`` x ``height`` image."""

    rotation: np.ndarray
    translation: np.ndarray
    focal_px: float
    width: int
    height: int

    @property
    def centre(self) -> np.ndarray:
        """The camera's position in world coordinates, ``-R^T t`` (3,)."""
        return -self.rotation.T @ self.translation

    @property
    def principal_point(self) -> tuple[float, float]:
        return ((self.width - 1) / 2.0, (self.height - 1) / 2.0)


@dataclass(frozen=True)
class Reprojection:
    """A GD image rendered into a target camera. ``intensity`` (H, W) or (H, W, 3) float32 (0 at holes),
    ``depth`` (H, W) float32 along the target's view axis (> 0 where covered, 0 at holes), ``hole``
    (H, W) bool (no kept triangle covers the pixel centre), ``boundary`` (H, W) bool (see
    :func:`boundary_mask`), and the mesh's kept / dropped triangle counts."""

    intensity: np.ndarray
    depth: np.ndarray
    hole: np.ndarray
    boundary: np.ndarray
    kept_triangles: int
    dropped_triangles: int

    @property
    def hole_fraction(self) -> float:
        return float(self.hole.mean())

    @property
    def mostly_holes(self) -> bool:
        return self.hole_fraction > MOSTLY_HOLES

    def as_gd(self, focal_px: float) -> GDImage:
        """The rendered view as a GD image (valid = covered), for a second reprojection."""
        return GDImage(self.intensity, self.depth, ~self.hole, float(focal_px))


# ------------------------------------------------------------------------------------ GD images
def make_gd_image(intensity: np.ndarray, depth: np.ndarray, focal_px: float, valid: np.ndarray | None = None) -> GDImage:
    """Validate and build a :class:`GDImage`.

    ``intensity`` (H, W) grey or (H, W, 3) RGB: uint8 (divided by 255) or float in [0, 1]; ``depth`` (H, W) float, in the
    baseline's units; ``valid`` (H, W) bool, optional (AND-ed with the depth's own validity).
    Depths that are <= 0, infinite, or more than 1e6 times off the median valid depth are masked
    (near-zero and infinite depth). Raises :class:`InvalidInputError` for NaN anywhere, wrong
    shapes or a bad focal length, :class:`ViewImageTooSmallError` below 2 x 2 px and
    :class:`NoValidDepthError` when nothing valid is left."""
    if not (isinstance(focal_px, (int, float, np.floating, np.integer)) and math.isfinite(focal_px) and focal_px > 0):
        raise InvalidInputError(f"focal_px must be finite and > 0, got {focal_px!r}")
    img = np.asarray(intensity)
    dep = np.asarray(depth)
    if dep.ndim != 2 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise InvalidInputError(f"intensity {img.shape} must be (H, W) or (H, W, 3) and depth {dep.shape} (H, W)")
    if img.shape[:2] != dep.shape:
        raise InvalidInputError(f"intensity {img.shape} and depth {dep.shape} differ in size")
    if min(dep.shape) < MIN_SIDE:
        raise ViewImageTooSmallError(f"GD image {dep.shape[1]}x{dep.shape[0]} is below {MIN_SIDE} px on a side")
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    elif img.dtype.kind in "fiu":
        img = img.astype(np.float32)  # a copy: clipped in place below
        if not np.isfinite(img).all():
            raise InvalidInputError("intensity contains NaN or infinite values")
        if img.size and (img.min() < -1e-6 or img.max() > 1 + 1e-6):
            raise InvalidInputError(f"float intensity must lie in [0, 1], got {img.min()}..{img.max()}")
        np.clip(img, 0.0, 1.0, out=img)
    else:
        raise InvalidInputError(f"unsupported intensity dtype {img.dtype}")
    if dep.dtype.kind not in "fiu":
        raise InvalidInputError(f"unsupported depth dtype {dep.dtype}")
    d = dep.astype(np.float64)
    if np.isnan(d).any():
        raise InvalidInputError("depth contains NaN (mark invalid depth with valid=False or 0 / inf)")
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        v = np.asarray(valid)
        if v.shape != d.shape:
            raise InvalidInputError(f"valid {v.shape} and depth {d.shape} differ in size")
        ok &= v.astype(bool)
    if ok.any():
        # Within a factor of 1e6 of the median: when the whole range is within 1e6 (nearly always),
        # every valid depth is, whatever the median (max <= 1e6 min puts med / 1e6 <= min and
        # max <= 1e6 med), and the median (a partition, 10 times the cost of min and max) is skipped.
        low, high = float(np.min(d, where=ok, initial=np.inf)), float(np.max(d, where=ok, initial=-np.inf))
        if high > low * _DEPTH_RANGE:
            med = float(np.median(d[ok], overwrite_input=True))  # a copy already
            ok &= (d >= med / _DEPTH_RANGE) & (d <= med * _DEPTH_RANGE)
    if not ok.any():
        raise NoValidDepthError("no valid depth in the GD image")
    out = np.where(ok, d, 0.0).astype(np.float32)
    ok &= out > 0  # float32 underflow
    if not ok.any():
        raise NoValidDepthError("no valid depth in the GD image")
    return GDImage(np.ascontiguousarray(img, np.float32), out, ok, float(focal_px))


# -------------------------------------------------------------------------------------- cameras
def reference_camera(gd: GDImage) -> Camera:
    """v0: identity pose at the world origin, looking down -z."""
    h, w = gd.shape
    return Camera(np.eye(3), np.zeros(3), gd.focal_px, w, h)


def scene_centre(gd: GDImage) -> np.ndarray:
    """``c = (0, 0, -1 / median(1 / D0))`` (3,), in v0's frame (the scene is on -z), over valid
    pixels: the harmonic median depth, robust to far outliers."""
    inv = 1.0 / gd.depth[gd.valid].astype(np.float64)
    return np.array([0.0, 0.0, -1.0 / float(np.median(inv))])


def max_disparity(gd: GDImage, baseline: float = 1.0) -> float:
    """``d_max = f b / min(D0)`` in px: the disparity of the nearest valid point (inverting
    ``D = f b / d``); ``baseline`` in the depth's units (1 for depth from ``depth_from_disparity``
    with its default baseline)."""
    _check_positive(baseline, "baseline")
    return float(gd.focal_px * baseline / float(np.min(gd.depth, where=gd.valid, initial=np.inf)))


def quad_radius(baseline: float, d_max: float, shift_px: float = SHIFT_PX) -> float:
    """``r_w = r_h = shift_px * b / d_max * sqrt(2) / 2`` (depth units): the half-side of the quad
    of corner cameras; ``shift_px`` = 96 in the paper. Finite for any finite positive inputs."""
    _check_positive(baseline, "baseline")
    _check_positive(d_max, "d_max")
    _check_positive(shift_px, "shift_px")
    r = shift_px * baseline / d_max * math.sqrt(2.0) / 2.0
    if not math.isfinite(r):
        raise InvalidInputError(f"quad radius is not finite (b={baseline}, d_max={d_max})")
    return r


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray, focal_px: float, width: int, height: int) -> Camera:
    """A camera at ``eye`` (3,) whose -z axis points at ``target`` (3,), with its y axis in the
    plane of ``up`` (3,) and the view direction (gluLookAt): rows of R are ``s = f x up / |.|``,
    ``u = s x f``, ``-f`` with ``f = (target - eye) / |target - eye|``; ``t = -R eye``."""
    eye, target, up = (np.asarray(a, np.float64).reshape(3) for a in (eye, target, up))
    fwd = target - eye
    n = np.linalg.norm(fwd)
    if not n > 0:
        raise InvalidInputError("look_at: eye and target coincide")
    fwd /= n
    side = np.cross(fwd, up)
    ns = np.linalg.norm(side)
    if not ns > 1e-12:
        raise InvalidInputError("look_at: up vector is parallel to the view direction")
    side /= ns
    upv = np.cross(side, fwd)
    rot = np.stack([side, upv, -fwd])
    return Camera(rot, -rot @ eye, float(focal_px), int(width), int(height))


def corner_cameras(
    gd: GDImage, baseline: float = 1.0, shift_px: float = SHIFT_PX, centre: np.ndarray | None = None
) -> list[Camera]:
    """v1..v4 at ``(+r, +r, 0)``, ``(-r, +r, 0)``, ``(-r, -r, 0)``, ``(+r, -r, 0)`` (in that
    order; ``r`` from :func:`quad_radius` with ``d_max`` from :func:`max_disparity`), each looking at
    :func:`scene_centre` with v0's up vector (0, 1, 0); ``centre``: that centre when the caller
    has it (a median over the image)."""
    r = quad_radius(baseline, max_disparity(gd, baseline), shift_px)
    c = scene_centre(gd) if centre is None else centre
    h, w = gd.shape
    up = np.array([0.0, 1.0, 0.0])
    return [look_at(np.array([sx * r, sy * r, 0.0]), c, up, gd.focal_px, w, h) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]


# --------------------------------------------------------------------------------- reprojection
def _affine(plane: np.ndarray, offset: float, depth: np.ndarray, shift: float) -> np.ndarray:
    """``(plane - offset) * depth + shift`` (H, W) float64, in place in ``plane`` (a fresh (H, W) array)."""
    plane -= offset
    plane *= depth
    plane += shift
    return plane


def _quad(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The (H-1, W-1) slices of a vertex grid at each pixel quad's corners p00, p01, p10, p11: the
    quad gives the upper triangle (p00, p01, p10) and the lower (p01, p11, p10), edge p01-p10 shared."""
    return a[:-1, :-1], a[:-1, 1:], a[1:, :-1], a[1:, 1:]


@dataclass(frozen=True)
class ContinuousTriangles:
    """The depth-edge half of :func:`reproject`'s triangle rule for one GD image, which depends on
    the target camera only through its distance from the source (``stretch_scale`` = source focal
    length x that distance): ``continuous`` holds the upper and the lower triangles' (H-1, W-1)
    bool masks, True where the triangle is no depth edge. Made by :func:`continuous_triangles`."""

    depth: np.ndarray  # the GD image's depth it was made from (compared by identity)
    max_relative_step: float
    max_stretch_px: float | None
    stretch_scale: float | None
    continuous: tuple[np.ndarray, np.ndarray]

    def matches(self, gd: GDImage, max_relative_step: float, max_stretch_px: float | None, distance: float) -> bool:
        """Whether this rule is the one for ``gd`` and these settings. The distance may differ by
        1e-9 of itself (cameras on one circle, whose distances differ in the last bits)."""
        if self.depth is not gd.depth or self.max_relative_step != max_relative_step or self.max_stretch_px != max_stretch_px:
            return False
        if self.stretch_scale is None:
            return True
        return math.isclose(self.stretch_scale, gd.focal_px * distance, rel_tol=1e-9, abs_tol=0.0)


def continuous_triangles(
    gd: GDImage, max_relative_step: float = MAX_RELATIVE_DEPTH_STEP, max_stretch_px: float | None = None, distance: float = 0.0
) -> ContinuousTriangles:
    """The triangles of ``gd``'s mesh that are no depth edge (:func:`reproject`'s docstring) for a
    target at ``distance`` (depth units) from the source camera."""
    h, w = gd.shape
    d = gd.depth.astype(np.float64)
    # The edge test reads the depth through a 3 x 3 median when the stretch rule is on: a lone noisy
    # pixel is no edge, a real step (a line of pixels) survives the median where it was.
    d_rule = d if max_stretch_px is None or min(h, w) < 3 else cv2.medianBlur(gd.depth.astype(np.float32), 3).astype(np.float64)
    d_rule = np.where(d_rule > 0, d_rule, d)
    d00, d01, d10, d11 = _quad(d_rule)
    shared_lo, shared_hi = np.minimum(d01, d10), np.maximum(d01, d10)
    stretch_scale = None if max_stretch_px is None else gd.focal_px * distance
    masks = []
    for first in (d00, d11):
        lo, hi = np.minimum(shared_lo, first), np.maximum(shared_hi, first)
        continuous = (hi - lo) <= max_relative_step * np.maximum(lo, 1e-300)
        if stretch_scale is not None and max_stretch_px is not None:  # a relative step with little parallax is no edge
            continuous |= stretch_scale * (1.0 / np.maximum(lo, 1e-300) - 1.0 / np.maximum(hi, 1e-300)) <= max_stretch_px
        masks.append(continuous)
    return ContinuousTriangles(gd.depth, max_relative_step, max_stretch_px, stretch_scale, (masks[0], masks[1]))


def _min3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a, b), c)


def _max3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a, b), c)


def reproject(
    gd: GDImage,
    source: Camera,
    target: Camera,
    max_relative_step: float = MAX_RELATIVE_DEPTH_STEP,
    with_boundary: bool = True,
    max_stretch_px: float | None = None,
    rule: ContinuousTriangles | None = None,
) -> Reprojection:
    """Render the GD image seen from ``source`` into ``target`` as a textured triangle mesh
    (module docstring): triangles with a vertex invalid or behind the target are dropped, and so
    are depth discontinuities: ``max |D_i - D_j| / min(D_i, D_j) > max_relative_step`` over their
    source depths and, when ``max_stretch_px`` is given, a parallax step across the triangle of more
    than ``max_stretch_px`` target pixels as well (:func:`triangle_stretch_px`). The rest are
    rasterised exactly with a z-buffer. Output arrays are (target.height, target.width) (plus the
    channel axis of a colour intensity); never NaN. ``with_boundary=False`` leaves the boundary mask
    empty (a render that is only looked at, never inpainted, does not need it). ``rule``: the
    depth-edge test already made for this GD image by :func:`continuous_triangles` (renders into
    several cameras at one distance from ``source`` share it); used when its settings match."""
    h, w = gd.shape
    if (source.width, source.height) != (w, h):
        raise InvalidInputError(f"source camera {source.width}x{source.height} does not match GD image {w}x{h}")
    if gd.intensity.shape[:2] != (h, w) or gd.valid.shape != (h, w):
        raise InvalidInputError("GD image: intensity, depth and valid differ in size")
    if not (np.isfinite(gd.depth).all() and np.isfinite(gd.intensity).all()):
        raise InvalidInputError("GD image contains NaN or infinite values (build it with make_gd_image)")
    th, tw = target.height, target.width
    if min(th, tw) < 1:
        raise ViewImageTooSmallError(f"target view {tw}x{th} is empty")
    channels = 1 if gd.intensity.ndim == 2 else int(gd.intensity.shape[2])

    # Per vertex, separably: the source ray (rx, ry, -1) at depth d, moved into the target frame,
    # x_t = d (M ray) + t with M = R_t R_s^T and t = t_t - M t_s (no (H, W, 3) temporaries).
    d = gd.depth.astype(np.float64)
    ok = gd.valid & (d > 0)
    rot = target.rotation @ source.rotation.T
    shift = target.translation - rot @ source.translation
    rx = (np.arange(w) - (w - 1) / 2.0) / gd.focal_px
    ry = -(np.arange(h)[:, None] - (h - 1) / 2.0) / gd.focal_px
    # (in place, in the same order of operations as the plain expressions: the same bits, fewer passes)
    xt, yt, z = (_affine(rot[k, 0] * rx + rot[k, 1] * ry, rot[k, 2], d, shift[k]) for k in range(3))
    np.negative(z, out=z)  # depth in the target
    near = 1e-3 * float(np.min(d, where=ok, initial=np.inf)) if ok.any() else 0.0
    ok &= z > near
    inverse_z = np.zeros_like(z)
    np.divide(1.0, z, out=inverse_z, where=ok)
    px, py = xt, yt  # (u, v) = (cx + f x / z, cy - f y / z)
    px *= target.focal_px
    px *= inverse_z
    px += (target.width - 1) / 2.0
    py *= target.focal_px
    py *= inverse_z
    np.subtract((th - 1) / 2.0, py, out=py)
    ok &= np.isfinite(px) & np.isfinite(py)

    # Per triangle, on grid slices (no gathers): the quad (p00, p01, p10, p11) gives the upper
    # triangle (p00, p01, p10) and the lower (p01, p11, p10); the shared edge p01-p10.
    distance = float(np.linalg.norm(target.centre - source.centre))
    if rule is None or not rule.matches(gd, max_relative_step, max_stretch_px, distance):
        rule = continuous_triangles(gd, max_relative_step, max_stretch_px, distance)
    o00, o01, o10, o11 = _quad(ok)
    edge_ok = o01 & o10
    total = 2 * (h - 1) * (w - 1)
    # float32 from here on (half the memory traffic): positions to 3e-5 px at 512 px, inverse depth
    # to 6e-8 relative; the z-buffer compares float32 depths, ties go to either fragment. A vertex
    # that is not ok may sit anywhere (no kept triangle uses it: the grid arithmetic masks it).
    pxf, pyf = px.astype(np.float32), py.astype(np.float32)
    izf = inverse_z.astype(np.float32)
    corners: dict[str, tuple[np.ndarray, ...]] = {"x": _quad(pxf), "y": _quad(pyf)}
    kept = 0
    kinds = []
    for kind, (o_first, continuous) in enumerate(zip((o00, o11), rule.continuous)):
        keep = edge_ok & o_first & continuous
        kept += int(np.count_nonzero(keep))
        kinds.append(_grid_triangles(keep, corners, kind, w, tw, th))
    izf = izf.ravel()
    # value / z (perspective), one flat plane per channel: 1-D gathers and scatters cost a third of
    # (N, 3) row ones
    planes = np.moveaxis(gd.intensity.reshape(h * w, channels), 1, 0) * izf

    zbuf = np.full(th * tw, np.inf, np.float32)
    fragments = []
    # Every triangle's first candidate pixel centre, the box's corner (the only one for 72 % of the
    # triangles of a 512 px corner view): tested on the grid of triangles as it is, with no gather.
    for grid in kinds:
        fragments.append(_corner_fragments(grid, izf, tw, zbuf))
    # The other candidates of bigger boxes, on those triangles' columns: boxes of up to 3 x 3
    # centres (98 % of them) in one pass over all their offsets, the rest through a repeat, in chunks.
    mesh, x0, y0, nx, ny = _big_triangles(kinds, pxf.ravel(), pyf.ravel())
    small = (nx <= _SMALL_BOX) & (ny <= _SMALL_BOX)
    sels = [np.flatnonzero(small & (nx > i) & (ny > j)) for i, j in _SMALL_BOX_OFFSETS]
    sel = np.concatenate(sels)
    steps = np.repeat(np.array(_SMALL_BOX_OFFSETS, np.float32), [len(s) for s in sels], axis=0)
    qx, qy = np.take(x0, sel) + steps[:, 0], np.take(y0, sel) + steps[:, 1]
    tri, pid, l0, l1, l2, dep = _fragments(mesh, sel, qx, qy, tw, izf, zbuf)
    fragments.append((mesh.a[tri], mesh.b[tri], mesh.c[tri], pid, l0, l1, l2, dep))
    more = np.flatnonzero(~small)
    count = nx[more] * ny[more] - 1
    csum = np.cumsum(count)
    start = 0
    while start < len(more):
        base = csum[start - 1] if start else 0
        stop = max(int(np.searchsorted(csum, base + _CHUNK, side="right")), start + 1)
        cnt = count[start:stop]
        rep = np.repeat(more[start:stop], cnt)
        offs = np.arange(len(rep)) - np.repeat(np.cumsum(cnt) - cnt, cnt) + 1
        nxr = nx[rep]
        qx, qy = (x0[rep] + offs % nxr).astype(np.float32), (y0[rep] + offs // nxr).astype(np.float32)
        tri, pid, l0, l1, l2, dep = _fragments(mesh, rep, qx, qy, tw, izf, zbuf)
        fragments.append((mesh.a[tri], mesh.b[tri], mesh.c[tri], pid, l0, l1, l2, dep))
        start = stop
    ibuf = np.zeros((channels, th * tw), np.float32)
    for va, vb, vc, pid, l0, l1, l2, dep in fragments:
        # Fragments at exactly the winning depth write their value (the last one where several
        # tie: equal depths are one surface).
        nearest = np.flatnonzero(dep == zbuf[pid])
        va, vb, vc, pid, l0, l1, l2, dep = (np.take(v, nearest) for v in (va, vb, vc, pid, l0, l1, l2, dep))
        for plane, out in zip(planes, ibuf):
            out[pid] = (l0 * np.take(plane, va) + l1 * np.take(plane, vb) + l2 * np.take(plane, vc)) * dep

    covered = np.isfinite(zbuf)
    depth = np.where(covered, zbuf, 0.0).reshape(th, tw).astype(np.float32)
    hole = ~covered.reshape(th, tw)
    depth[depth <= 0] = 0.0
    hole |= depth <= 0
    np.clip(ibuf, 0.0, 1.0, out=ibuf)
    ibuf[:, hole.ravel()] = 0.0
    inten = (
        ibuf[0].reshape(th, tw)
        if gd.intensity.ndim == 2
        else np.ascontiguousarray(np.moveaxis(ibuf, 0, 1)).reshape(th, tw, channels)
    )
    boundary = boundary_mask(hole, depth, ~hole, max_relative_step) if with_boundary else np.zeros_like(hole)
    return Reprojection(inten, depth, hole, boundary, kept, total - kept)


@dataclass(frozen=True)
class _ScreenMesh:
    """The kept triangles in target pixels, one (T,) column per quantity: vertex indices ``a``,
    ``b``, ``c`` (flat, into the source grid), positions ``x*``/``y*`` and the barycentric denominator."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    xa: np.ndarray
    xb: np.ndarray
    xc: np.ndarray
    ya: np.ndarray
    yb: np.ndarray
    yc: np.ndarray
    denom: np.ndarray


def _fragments(
    mesh: _ScreenMesh, rep: np.ndarray | None, qx: np.ndarray, qy: np.ndarray, tw: int, inverse_z: np.ndarray, zbuf: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Test candidate pixel centres ``(qx, qy)`` against triangles ``rep`` (all of them, in order,
    when None); the inside ones go into the z-buffer ``zbuf`` (flat, in place: an unbuffered
    minimum, O(n); a sort by pixel and depth cost twice the whole rasterisation). Returns the
    fragments ``(triangle, pixel, l0, l1, l2, depth)``."""

    def col(v: np.ndarray) -> np.ndarray:
        return v if rep is None else v[rep]

    xc, yc = col(mesh.xc), col(mesh.yc)
    dx, dy = qx - xc, qy - yc
    den = col(mesh.denom)
    l0 = ((col(mesh.yb) - yc) * dx + (xc - col(mesh.xb)) * dy) / den
    l1 = ((yc - col(mesh.ya)) * dx + (col(mesh.xa) - xc) * dy) / den
    l2 = 1.0 - l0 - l1
    eps = -1e-5  # float32 barycentrics: a centre on a shared edge must land in one of its triangles
    inside = np.flatnonzero((l0 >= eps) & (l1 >= eps) & (l2 >= eps))
    tri = inside if rep is None else rep[inside]
    l0, l1, l2 = l0[inside], l1[inside], l2[inside]
    pid = qy[inside].astype(np.int64) * tw + qx[inside].astype(np.int64)
    inv = l0 * inverse_z[mesh.a[tri]] + l1 * inverse_z[mesh.b[tri]] + l2 * inverse_z[mesh.c[tri]]
    good = inv > 0
    if not good.all():
        tri, l0, l1, l2, pid, inv = tri[good], l0[good], l1[good], l2[good], pid[good], inv[good]
    dep = (1.0 / inv).astype(zbuf.dtype)  # compared with the z-buffer for equality: the same dtype
    np.minimum.at(zbuf, pid, dep)
    return tri, pid, l0, l1, l2, dep


@dataclass(frozen=True)
class _GridTriangles:
    """One kind of triangle (``kind`` 0: upper (p00, p01, p10), 1: lower (p01, p11, p10)) over the
    (H-1, W-1) grid of pixel quads, in target pixels: corner positions ``xa`` .. ``yc``, the
    barycentric denominator, the bounding box's first pixel centre ``(x0, y0)`` and its size
    ``(nx, ny)`` (float32, exact integers where ``live``), and ``live``: kept by the triangle rule,
    with a pixel centre in its clipped box and not degenerate. ``width``: the source grid's."""

    kind: int
    width: int
    xa: np.ndarray
    xb: np.ndarray
    xc: np.ndarray
    ya: np.ndarray
    yb: np.ndarray
    yc: np.ndarray
    denom: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    live: np.ndarray

    def vertices(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat source-grid indices of the three vertices of the triangles in ``cells`` (flat quad indices)."""
        p00 = cells + cells // (self.width - 1)
        if self.kind == 0:
            return p00, p00 + 1, p00 + self.width
        return p00 + 1, p00 + self.width + 1, p00 + self.width


def _grid_triangles(
    keep: np.ndarray, corners: dict[str, tuple[np.ndarray, ...]], kind: int, width: int, tw: int, th: int
) -> _GridTriangles:
    """:class:`_GridTriangles` of ``kind`` from the quad corners of the projected vertex grid
    (``corners["x"]``, ``corners["y"]``: (p00, p01, p10, p11) slices) and the rule's ``keep``."""
    order = (0, 1, 2) if kind == 0 else (1, 3, 2)
    xa, xb, xc = (corners["x"][k] for k in order)
    ya, yb, yc = (corners["y"][k] for k in order)
    with np.errstate(invalid="ignore", over="ignore"):  # vertices that are not ok: masked by keep
        x0 = np.maximum(np.ceil(_min3(xa, xb, xc) - 1e-4), 0)
        x1 = np.minimum(np.floor(_max3(xa, xb, xc) + 1e-4), tw - 1)
        y0 = np.maximum(np.ceil(_min3(ya, yb, yc) - 1e-4), 0)
        y1 = np.minimum(np.floor(_max3(ya, yb, yc) + 1e-4), th - 1)
        nx, ny = x1 - x0 + 1, y1 - y0 + 1
        denom = (yb - yc) * (xa - xc) + (xc - xb) * (ya - yc)
        live = keep & (nx > 0) & (ny > 0) & (np.abs(denom) > 1e-6)
    return _GridTriangles(kind, width, xa, xb, xc, ya, yb, yc, denom, x0, y0, nx, ny, live)


def _corner_fragments(tri: _GridTriangles, inverse_z: np.ndarray, tw: int, zbuf: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each live triangle of ``tri`` against its box's first pixel centre ``(x0, y0)``, computed over
    the whole grid (no gathers until the inside ones are known); into the z-buffer ``zbuf`` (flat,
    in place). Returns the fragments ``(a, b, c, pixel, l0, l1, l2, depth)``, ``a, b, c`` the
    vertices' flat source indices. The arithmetic is :func:`_fragments`' (the same float32 values)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # dead triangles: masked below
        dx, dy = tri.x0 - tri.xc, tri.y0 - tri.yc
        l0 = ((tri.yb - tri.yc) * dx + (tri.xc - tri.xb) * dy) / tri.denom
        l1 = ((tri.yc - tri.ya) * dx + (tri.xa - tri.xc) * dy) / tri.denom
        l2 = 1.0 - l0 - l1
    eps = -1e-5  # float32 barycentrics: a centre on a shared edge must land in one of its triangles
    cells = np.flatnonzero(tri.live & (l0 >= eps) & (l1 >= eps) & (l2 >= eps))
    l0, l1, l2 = l0.ravel()[cells], l1.ravel()[cells], l2.ravel()[cells]
    a, b, c = tri.vertices(cells)
    pid = tri.y0.ravel()[cells].astype(np.int64) * tw + tri.x0.ravel()[cells].astype(np.int64)
    inv = l0 * inverse_z[a] + l1 * inverse_z[b] + l2 * inverse_z[c]
    good = inv > 0
    if not good.all():
        a, b, c, pid, l0, l1, l2, inv = (v[good] for v in (a, b, c, pid, l0, l1, l2, inv))
    dep = (1.0 / inv).astype(zbuf.dtype)
    np.minimum.at(zbuf, pid, dep)
    return a, b, c, pid, l0, l1, l2, dep


def _big_triangles(
    kinds: list[_GridTriangles], px: np.ndarray, py: np.ndarray
) -> tuple[_ScreenMesh, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The live triangles whose box holds more than one pixel centre, as columns (both kinds, in
    grid order): ``(mesh, x0, y0, nx, ny)``, the box's first centre (float32) and size (int64).
    ``px``, ``py``: the vertices' target positions, flat (the corners are read there by vertex
    index: the grid slices are strided, and flattening one copies the whole grid)."""
    parts: list[list[np.ndarray]] = [[] for _ in range(14)]
    for tri in kinds:
        cells = np.flatnonzero(tri.live & ((tri.nx > 1) | (tri.ny > 1)))
        a, b, c = tri.vertices(cells)
        columns = [a, b, c] + [np.take(px, v) for v in (a, b, c)] + [np.take(py, v) for v in (a, b, c)]
        columns += [tri.denom.ravel()[cells], tri.x0.ravel()[cells], tri.y0.ravel()[cells]]
        columns += [tri.nx.ravel()[cells].astype(np.int64), tri.ny.ravel()[cells].astype(np.int64)]
        for part, column in zip(parts, columns):
            part.append(column)
    joined = [np.concatenate(part) for part in parts]
    return _ScreenMesh(*joined[:10]), joined[10], joined[11], joined[12], joined[13]


# ----------------------------------------------------------------------------------- boundaries
_EIGHT = np.ones((3, 3), np.uint8)


def _dilate(mask: np.ndarray) -> np.ndarray:
    """Binary dilation of ``mask`` (H, W) bool or uint8 by a 3 x 3 square, nothing outside the
    image (as scipy's ``binary_dilation``): (H, W) bool."""
    grown = cv2.dilate(mask.astype(np.uint8), _EIGHT, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return np.asarray(grown, bool)


def boundary_mask(
    hole: np.ndarray, depth: np.ndarray, valid: np.ndarray, max_relative_step: float = MAX_RELATIVE_DEPTH_STEP
) -> np.ndarray:
    """B (H, W) bool: valid non-hole 8-neighbours of each hole component on its foreground side
    (module docstring). ``hole``, ``depth`` (> 0 where ``valid``) and ``valid`` are (H, W)."""
    hole = np.asarray(hole, bool)
    valid = np.asarray(valid, bool) & ~hole & np.isfinite(depth) & (np.asarray(depth) > 0)
    out = np.zeros(hole.shape, bool)
    if not hole.any() or not valid.any():
        return out
    labels, n = ndimage.label(hole, structure=np.ones((3, 3), bool))
    border = _dilate(hole) & valid
    if not border.any():
        return out
    # each border pixel's hole component: the largest label among its 8-neighbours (OpenCV's
    # dilation, exact on float32 labels below 2^24; a fifth of scipy's grey dilation's time)
    lab = np.where(border, cv2.dilate(labels.astype(np.float32), _EIGHT).astype(np.int64), 0)
    inv = np.zeros(hole.shape, np.float64)
    inv[border] = 1.0 / depth[border].astype(np.float64)
    # Per component, over its border pixels only: the largest 1/D (nearest) and the smallest.
    owner, border_inv = lab[border], inv[border]
    near = np.full(n + 1, -np.inf)
    far = np.full(n + 1, np.inf)
    np.maximum.at(near, owner, border_inv)
    np.minimum.at(far, owner, border_inv)
    near, far = near[1:], far[1:]
    has = np.isfinite(near) & np.isfinite(far) & (far > 0) & (near > far * (1.0 + max_relative_step))
    mid = np.full(n, np.inf)  # a component with no border (or no depth step) marks nothing
    mid[has] = (near[has] + far[has]) / 2.0
    mid_px = np.concatenate([[np.inf], mid])[lab]
    out = border & (inv > mid_px)
    return out


def crack_fraction(hole: np.ndarray) -> float:
    """The fraction of the image in **cracks**: thin holes inside the picture. A triangle dropped in
    a continuous surface leaves a line a pixel or two wide; a disocclusion at a depth edge is as wide
    as the parallax step (more than ``max_stretch_px``), and what the source never saw is a band
    along the border. So: the hole pixels (``hole`` (H, W) bool) that an opening by a 3 x 3 square
    removes, in 8-connected pieces that touch neither a wider hole (its ragged rim) nor the image
    border. A crack that runs into a disocclusion is not counted: a lower bound."""
    hole = np.asarray(hole, bool)
    if not hole.any():
        return 0.0
    # a binary opening with nothing outside the image (scipy's border_value 0), by OpenCV on uint8
    thick = _dilate(cv2.erode(hole.astype(np.uint8), _EIGHT, borderType=cv2.BORDER_CONSTANT, borderValue=0))
    thin = hole & ~thick
    if not thin.any():
        return 0.0
    labels, n = ndimage.label(thin, structure=np.ones((3, 3), bool))
    attached = np.unique(labels[_dilate(thick) & thin])
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    crack = np.ones(n + 1, bool)
    crack[0] = False
    crack[attached] = False
    crack[edge] = False
    return float(crack[labels].mean())


# --------------------------------------------------------------------------- double reprojection
def corner_views(gd: GDImage, baseline: float = 1.0, shift_px: float = SHIFT_PX) -> list[Reprojection]:
    """v0 rendered into the four corner cameras (order of :func:`corner_cameras`)."""
    ref = reference_camera(gd)
    return [reproject(gd, ref, cam) for cam in corner_cameras(gd, baseline, shift_px)]


def double_reprojection(gd: GDImage, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """v0 -> ``camera`` -> v0: ``(hole, boundary)`` (H, W) bool in v0's frame. ``hole``: v0 pixels
    that the round trip leaves uncovered and where v0 has valid depth (the training targets);
    ``boundary``: :func:`boundary_mask` of those holes with v0's own depth."""
    ref = reference_camera(gd)
    there = reproject(gd, ref, camera)
    if there.hole.all():
        hole = gd.valid.copy()
    else:
        back = reproject(there.as_gd(camera.focal_px), camera, ref)
        hole = back.hole & gd.valid
    return hole, boundary_mask(hole, gd.depth, gd.valid)


def training_holes(gd: GDImage, cameras: Sequence[Camera]) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`double_reprojection` for each camera (normally the four of :func:`corner_cameras`)."""
    return [double_reprojection(gd, cam) for cam in cameras]


def needs_inpainting(holes: np.ndarray | Sequence[np.ndarray]) -> tuple[bool, str]:
    """Whether a scene's views need inpainting, and why (for the stage record). ``holes``: one
    (H, W) bool mask or a sequence of them (one per corner view)."""
    masks = (
        [np.asarray(holes, bool)]
        if isinstance(holes, np.ndarray) and np.ndim(holes) == 2
        else [np.asarray(m, bool) for m in holes]
    )
    if not masks or all(not m.any() for m in masks):
        return False, "no_holes: the reprojections leave no holes"
    worst = max(float(m.mean()) for m in masks if m.size)
    if worst > MOSTLY_HOLES:
        return True, f"mostly_holes: holes cover up to {100 * worst:.1f} % of a view"
    return True, f"holes: up to {100 * worst:.2f} % of a view"


def _check_positive(x: float, name: str) -> None:
    if not (isinstance(x, (int, float, np.floating, np.integer)) and math.isfinite(x) and x > 0):
        raise InvalidInputError(f"{name} must be finite and > 0, got {x!r}")
