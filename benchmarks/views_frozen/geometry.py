"""View synthesis geometry (issue 8, sections 1, 2, 5 and 8): GD images, the quad of corner
cameras, textured-mesh reprojection with holes, and double-reprojection training holes.

Pure numpy/scipy; no torch, no web or database imports.

Conventions
-----------
* A **GD image** is a grey intensity ``I`` (H, W) float32 in [0, 1] and a depth ``D`` (H, W)
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
target camera, or when its vertices' source depths differ in relative depth by more than 0.1:
``max_ij |D_i - D_j| / min(D_i, D_j) > 0.1`` (a depth discontinuity). The kept triangles are
rasterised **exactly** (every target pixel centre inside a projected triangle, vectorised over
all triangles' bounding boxes in numpy) with a z-buffer (nearest wins). Within a triangle the
inverse depth is interpolated linearly in screen space (exact for a planar triangle) and the
intensity perspective-correctly. Target pixels no kept triangle covers are **holes** (this includes
regions outside the source's field of view). No anti-aliasing: intensities are sampled at pixel
centres, so resampling blurs like bilinear interpolation. The mesh ends at the source's border
pixel centres, so a target pixel whose centre falls just outside that footprint is a hole (a round
trip v0 -> v' -> v0 loses up to one pixel along v0's border on the sides v' does not see).
Cost: vectorised over triangles (per-vertex columns, an unbuffered minimum for the z-buffer),
~0.09 s for 256 x 256 and ~0.3 s for 512 x 512 on one core of the shared 2-core machine.

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

import numpy as np
from scipy import ndimage

from pipeline.errors import InvalidInputError

__all__ = [
    "MAX_RELATIVE_DEPTH_STEP",
    "MIN_SIDE",
    "SHIFT_PX",
    "Camera",
    "GDImage",
    "NoValidDepthError",
    "Reprojection",
    "ViewImageTooSmallError",
    "boundary_mask",
    "corner_cameras",
    "corner_views",
    "double_reprojection",
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


class NoValidDepthError(InvalidInputError):
    """Nothing in the GD image has a usable (finite, positive, non-degenerate) depth."""

    code = "no_valid_depth"


class ViewImageTooSmallError(InvalidInputError):
    """The image has no 2 x 2 pixel quad to build a mesh from."""

    code = "image_too_small"


# ------------------------------------------------------------------------------------ data types
@dataclass(frozen=True)
class GDImage:
    """A grey + depth image. ``intensity`` (H, W) float32 in [0, 1]; ``depth`` (H, W) float32,
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
    """A GD image rendered into a target camera. ``intensity`` (H, W) float32 (0 at holes),
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

    ``intensity`` (H, W): uint8 (divided by 255) or float in [0, 1]; ``depth`` (H, W) float, in the
    baseline's units; ``valid`` (H, W) bool, optional (AND-ed with the depth's own validity).
    Depths that are <= 0, infinite, or more than 1e6 times off the median valid depth are masked
    (near-zero and infinite depth). Raises :class:`InvalidInputError` for NaN anywhere, wrong
    shapes or a bad focal length, :class:`ViewImageTooSmallError` below 2 x 2 px and
    :class:`NoValidDepthError` when nothing valid is left."""
    if not (isinstance(focal_px, (int, float, np.floating, np.integer)) and math.isfinite(focal_px) and focal_px > 0):
        raise InvalidInputError(f"focal_px must be finite and > 0, got {focal_px!r}")
    img = np.asarray(intensity)
    dep = np.asarray(depth)
    if img.ndim != 2 or dep.ndim != 2:
        raise InvalidInputError(f"intensity {img.shape} and depth {dep.shape} must be (H, W)")
    if img.shape != dep.shape:
        raise InvalidInputError(f"intensity {img.shape} and depth {dep.shape} differ in size")
    if min(dep.shape) < MIN_SIDE:
        raise ViewImageTooSmallError(f"GD image {dep.shape[1]}x{dep.shape[0]} is below {MIN_SIDE} px on a side")
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    elif img.dtype.kind in "fiu":
        img = img.astype(np.float32)
        if np.isnan(img).any() or not np.isfinite(img).all():
            raise InvalidInputError("intensity contains NaN or infinite values")
        if img.size and (img.min() < -1e-6 or img.max() > 1 + 1e-6):
            raise InvalidInputError(f"float intensity must lie in [0, 1], got {img.min()}..{img.max()}")
        img = np.clip(img, 0.0, 1.0)
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
        med = float(np.median(d[ok]))
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
    return float(gd.focal_px * baseline / float(gd.depth[gd.valid].min()))


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


def corner_cameras(gd: GDImage, baseline: float = 1.0, shift_px: float = SHIFT_PX) -> list[Camera]:
    """v1..v4 at ``(+r, +r, 0)``, ``(-r, +r, 0)``, ``(-r, -r, 0)``, ``(+r, -r, 0)`` (in that
    order; ``r`` from :func:`quad_radius` with ``d_max`` from :func:`max_disparity`), each looking at
    :func:`scene_centre` with v0's up vector (0, 1, 0)."""
    r = quad_radius(baseline, max_disparity(gd, baseline), shift_px)
    c = scene_centre(gd)
    h, w = gd.shape
    up = np.array([0.0, 1.0, 0.0])
    return [look_at(np.array([sx * r, sy * r, 0.0]), c, up, gd.focal_px, w, h) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]


# --------------------------------------------------------------------------------- reprojection
def _unproject(gd: GDImage, cam: Camera) -> np.ndarray:
    """World points (H, W, 3) of every pixel (garbage where invalid)."""
    h, w = gd.shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = gd.depth.astype(np.float64)
    pc = np.stack([(u - cx) * d / gd.focal_px, -(v - cy) * d / gd.focal_px, -d], axis=-1)
    return (pc - cam.translation) @ cam.rotation  # R^T (x - t), row-vector form


def _triangles(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat vertex indices of the 2 (H-1)(W-1) triangles as three (T,) columns: each quad
    (p00, p01, p10, p11) -> (p00, p01, p10) and (p01, p11, p10). Columns, not a (T, 3) array:
    numpy reduces over a short last axis an order of magnitude slower than it combines columns."""
    idx = np.arange(h * w).reshape(h, w)
    p00, p01 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    p10, p11 = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([p00, p01]), np.concatenate([p01, p11]), np.concatenate([p10, p10])


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
) -> Reprojection:
    """Render the GD image seen from ``source`` into ``target`` as a textured triangle mesh
    (module docstring): triangles with a vertex invalid or behind the target, or with
    ``max |D_i - D_j| / min(D_i, D_j) > max_relative_step`` over their source depths, are dropped;
    the rest are rasterised exactly with a z-buffer. Output arrays are (target.height,
    target.width); never NaN. ``with_boundary=False`` leaves the boundary mask empty (a render
    that is only looked at, never inpainted, does not need it)."""
    h, w = gd.shape
    if (source.width, source.height) != (w, h):
        raise InvalidInputError(f"source camera {source.width}x{source.height} does not match GD image {w}x{h}")
    if gd.intensity.shape != (h, w) or gd.valid.shape != (h, w):
        raise InvalidInputError("GD image: intensity, depth and valid differ in size")
    if not (np.isfinite(gd.depth).all() and np.isfinite(gd.intensity).all()):
        raise InvalidInputError("GD image contains NaN or infinite values (build it with make_gd_image)")
    th, tw = target.height, target.width
    if min(th, tw) < 1:
        raise ViewImageTooSmallError(f"target view {tw}x{th} is empty")
    a, b, c = _triangles(h, w)
    total = len(a)
    d_src = gd.depth.ravel().astype(np.float64)
    ok_v = gd.valid.ravel() & (d_src > 0)
    world = _unproject(gd, source).reshape(-1, 3)
    pc = world @ target.rotation.T + target.translation
    z = -pc[:, 2]  # depth in the target
    near = 1e-3 * float(d_src[ok_v].min()) if ok_v.any() else 0.0
    ok_v = ok_v & (z > near)
    zs = np.where(ok_v, z, 1.0)
    tcx, tcy = (tw - 1) / 2.0, (th - 1) / 2.0
    px = tcx + target.focal_px * pc[:, 0] / zs
    py = tcy - target.focal_px * pc[:, 1] / zs

    keep = ok_v[a] & ok_v[b] & ok_v[c]
    da, db, dc = d_src[a], d_src[b], d_src[c]
    dmin = _min3(da, db, dc)
    keep &= (_max3(da, db, dc) - dmin) <= max_relative_step * np.maximum(dmin, 1e-300)
    a, b, c = a[keep], b[keep], c[keep]
    kept = len(a)
    finite = (
        np.isfinite(px[a])
        & np.isfinite(px[b])
        & np.isfinite(px[c])
        & np.isfinite(py[a])
        & np.isfinite(py[b])
        & np.isfinite(py[c])
    )
    a, b, c = a[finite], b[finite], c[finite]
    xa, xb, xc, ya, yb, yc = px[a], px[b], px[c], py[a], py[b], py[c]
    inverse_z = 1.0 / zs  # inverse target depth per vertex
    intensity = gd.intensity.ravel().astype(np.float64) * inverse_z  # intensity / z, for perspective correction

    # screen-space bounding boxes, clipped to the target
    x0 = np.maximum(np.ceil(_min3(xa, xb, xc) - 1e-9), 0).astype(np.int64)
    x1 = np.minimum(np.floor(_max3(xa, xb, xc) + 1e-9), tw - 1).astype(np.int64)
    y0 = np.maximum(np.ceil(_min3(ya, yb, yc) - 1e-9), 0).astype(np.int64)
    y1 = np.minimum(np.floor(_max3(ya, yb, yc) + 1e-9), th - 1).astype(np.int64)
    nx, ny = x1 - x0 + 1, y1 - y0 + 1
    denom = (yb - yc) * (xa - xc) + (xc - xb) * (ya - yc)
    live = (nx > 0) & (ny > 0) & (np.abs(denom) > 1e-12)
    sel = np.flatnonzero(live)
    count = (nx * ny)[sel]
    mesh = _ScreenMesh(
        xa,
        xb,
        xc,
        ya,
        yb,
        yc,
        x0,
        y0,
        nx,
        denom,
        inverse_z[a],
        inverse_z[b],
        inverse_z[c],
        intensity[a],
        intensity[b],
        intensity[c],
    )

    zbuf = np.full(th * tw, np.inf)
    ibuf = np.zeros(th * tw)
    start = 0
    csum = np.cumsum(count)
    while start < len(sel):
        base = csum[start - 1] if start else 0
        stop = int(np.searchsorted(csum, base + _CHUNK, side="right"))
        stop = max(stop, start + 1)
        _raster_chunk(sel[start:stop], count[start:stop], mesh, tw, zbuf, ibuf)
        start = stop

    covered = np.isfinite(zbuf)
    depth = np.where(covered, zbuf, 0.0).reshape(th, tw).astype(np.float32)
    inten = np.clip(np.where(covered, ibuf, 0.0), 0.0, 1.0).reshape(th, tw).astype(np.float32)
    hole = ~covered.reshape(th, tw)
    depth[depth <= 0] = 0.0
    hole |= depth <= 0
    inten[hole] = 0.0
    boundary = boundary_mask(hole, depth, ~hole, max_relative_step) if with_boundary else np.zeros_like(hole)
    return Reprojection(inten, depth, hole, boundary, kept, total - kept)


@dataclass(frozen=True)
class _ScreenMesh:
    """The kept triangles in target pixels, one (T,) column per vertex quantity: positions
    ``x*``/``y*``, clipped bounding-box corner ``x0``/``y0`` and width ``nx``, the barycentric
    denominator, inverse depth ``w*`` and intensity over depth ``i*`` at vertices a, b, c."""

    xa: np.ndarray
    xb: np.ndarray
    xc: np.ndarray
    ya: np.ndarray
    yb: np.ndarray
    yc: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    nx: np.ndarray
    denom: np.ndarray
    wa: np.ndarray
    wb: np.ndarray
    wc: np.ndarray
    ia: np.ndarray
    ib: np.ndarray
    ic: np.ndarray


def _raster_chunk(sel: np.ndarray, count: np.ndarray, mesh: _ScreenMesh, tw: int, zbuf: np.ndarray, ibuf: np.ndarray) -> None:
    """Rasterise triangles ``sel`` into the z-buffer ``zbuf`` / intensity ``ibuf`` (flat, in place)."""
    n = int(count.sum())
    rep = np.repeat(sel, count)
    offs = np.arange(n) - np.repeat(np.cumsum(count) - count, count)
    nxr = mesh.nx[rep]
    qx = (mesh.x0[rep] + offs % nxr).astype(np.float64)
    qy = (mesh.y0[rep] + offs // nxr).astype(np.float64)
    xa, xb, xc = mesh.xa[rep], mesh.xb[rep], mesh.xc[rep]
    ya, yb, yc = mesh.ya[rep], mesh.yb[rep], mesh.yc[rep]
    den = mesh.denom[rep]
    l0 = ((yb - yc) * (qx - xc) + (xc - xb) * (qy - yc)) / den
    l1 = ((yc - ya) * (qx - xc) + (xa - xc) * (qy - yc)) / den
    l2 = 1.0 - l0 - l1
    eps = -1e-7
    inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
    if not inside.any():
        return
    rep, l0, l1, l2 = rep[inside], l0[inside], l1[inside], l2[inside]
    pid = qy[inside].astype(np.int64) * tw + qx[inside].astype(np.int64)
    inv = l0 * mesh.wa[rep] + l1 * mesh.wb[rep] + l2 * mesh.wc[rep]
    good = inv > 0
    if not good.all():
        rep, l0, l1, l2, pid, inv = rep[good], l0[good], l1[good], l2[good], pid[good], inv[good]
    val = (l0 * mesh.ia[rep] + l1 * mesh.ib[rep] + l2 * mesh.ic[rep]) / inv
    dep = 1.0 / inv
    # z-buffer: the nearest fragment per pixel (an unbuffered minimum, O(n); a sort by pixel
    # and depth cost twice the whole rasterisation). Fragments at exactly the winning depth
    # then write their intensity; equal depths are one surface, so any of them will do.
    np.minimum.at(zbuf, pid, dep)
    nearest = dep == zbuf[pid]
    ibuf[pid[nearest]] = val[nearest]


# ----------------------------------------------------------------------------------- boundaries
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
    eight = np.ones((3, 3), bool)
    labels, n = ndimage.label(hole, structure=eight)
    border = ndimage.binary_dilation(hole, structure=eight) & valid
    if not border.any():
        return out
    lab = ndimage.grey_dilation(labels, footprint=eight)
    lab = np.where(border, lab, 0)
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
