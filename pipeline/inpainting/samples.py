"""Training and evaluation samples: holes made by double reprojection (a view reprojected to a
corner camera and back, as KeystoneDepth trains its inpainting networks) of GD images, and the
built-in GD images from scikit-image's Middlebury Motorcycle."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .fill import classical_init, normalise_known

if TYPE_CHECKING:
    from ..views import GDImage

MOTORCYCLE_FOCAL_PX = 3979.911  # MiddEval3 Motorcycle calib (cam0), full resolution


@dataclass(frozen=True)
class Sample:
    """One training / evaluation sample (all (H, W) float32): ``intensity`` in [0, 1], ``dhat``
    normalised inverse depth over known pixels, ``hole`` (1 = hole), ``boundary``, ``known`` (1 where
    ground truth exists: valid depth). ``init`` (2, H, W): the classical fill the guided networks
    refine (:func:`classical_init`); computed on first use when not given."""

    intensity: np.ndarray
    dhat: np.ndarray
    hole: np.ndarray
    boundary: np.ndarray
    known: np.ndarray
    init: np.ndarray | None = None

    def guide(self) -> np.ndarray:
        if self.init is not None:
            return self.init
        fill = (self.hole > 0) | (self.known <= 0)
        return classical_init(self.intensity, self.dhat, fill)


def make_samples(gd_images: Iterable[GDImage], shift_px: float | None = None) -> list[Sample]:
    """Training holes by double reprojection (:func:`pipeline.views.training_holes`) of each GD
    image towards its four corner cameras: one :class:`Sample` per (image, camera) whose hole is
    non-empty. ``shift_px`` defaults to 96 scaled to the image (96 * min(H, W) / 512, at least 4)."""
    from ..views import corner_cameras, training_holes

    samples = []
    for gd in gd_images:
        h, w = gd.shape
        shift = shift_px if shift_px is not None else max(4.0, 96.0 * min(h, w) / 512.0)
        for hole, boundary in training_holes(gd, corner_cameras(gd, shift_px=shift)):
            if not hole.any():
                continue
            known = gd.valid & ~hole
            dhat, _, _ = normalise_known(gd.depth, known)
            intensity = gd.intensity.astype(np.float32)
            samples.append(
                Sample(
                    intensity,
                    dhat,
                    hole.astype(np.float32),
                    boundary.astype(np.float32),
                    gd.valid.astype(np.float32),
                    classical_init(intensity, dhat, ~known),
                )
            )
    return samples


def _motorcycle() -> tuple[np.ndarray, np.ndarray]:
    from skimage import data

    left, _, disp = data.stereo_motorcycle()
    grey = cv2.cvtColor(np.asarray(left), cv2.COLOR_RGB2GRAY)
    return grey, np.asarray(disp, np.float32)


def builtin_gd_images(size: int, train_fraction: float = 0.6, stride: int | None = None) -> tuple[list[GDImage], list[GDImage]]:
    """GD images from scikit-image's Motorcycle (left view + ground-truth disparity; depth
    ``D = f / d`` up to scale, invalid disparity -> invalid depth), downscaled so the image is
    2 and 3 crop sizes high. Returns ``(train, test)``: ``size`` x ``size`` crops whose columns lie in
    the left ``train_fraction`` of the image (plus their horizontal flips) and held-out crops from
    the remaining right part (no flips), so no test pixel is ever seen in training."""
    from ..views import make_gd_image

    grey, disp = _motorcycle()
    train, test = [], []
    for scale_h in (2, 3):
        s = scale_h * size / grey.shape[0]
        w = round(grey.shape[1] * s)
        g = cv2.resize(grey, (w, scale_h * size), interpolation=cv2.INTER_AREA)
        d = cv2.resize(disp, (w, scale_h * size), interpolation=cv2.INTER_NEAREST) * s
        ok = np.isfinite(d) & (d > 0)
        depth = np.where(ok, 1.0 / np.where(ok, d, 1.0), 0.0) * MOTORCYCLE_FOCAL_PX * s
        split = int(w * train_fraction)
        st = stride or max(4, size // 2)
        for y in range(0, g.shape[0] - size + 1, st):
            for x in range(0, split - size + 1, st):
                sl = (slice(y, y + size), slice(x, x + size))
                if ok[sl].mean() < 0.5:
                    continue
                for flip in (False, True):
                    gi, di, vi = g[sl], depth[sl], ok[sl]
                    if flip:
                        gi, di, vi = gi[:, ::-1], di[:, ::-1], vi[:, ::-1]
                    train.append(
                        make_gd_image(
                            np.ascontiguousarray(gi), np.ascontiguousarray(di), MOTORCYCLE_FOCAL_PX * s, np.ascontiguousarray(vi)
                        )
                    )
            for x in range(split, w - size + 1, st):
                sl = (slice(y, y + size), slice(x, x + size))
                if ok[sl].mean() < 0.5:
                    continue
                test.append(make_gd_image(g[sl], depth[sl], MOTORCYCLE_FOCAL_PX * s, ok[sl]))
    return train, test


def crop_gd_images(
    gd_images: Iterable[GDImage], size: int, stride: int | None = None, min_valid: float = 0.5, flips: bool = True
) -> list[GDImage]:
    """``size`` x ``size`` training crops of whole GD images (e.g. the catalogue's own v0 views),
    each downscaled first so its shorter side is at most 3 crop sizes (focal scaled with it), plus
    horizontal flips. Crops with less than ``min_valid`` valid depth are dropped."""
    from ..views import make_gd_image

    crops = []
    for gd in gd_images:
        h, w = gd.shape
        s = min(1.0, 3 * size / min(h, w))
        if s < 1.0:
            new = (max(size, round(w * s)), max(size, round(h * s)))
            intensity = cv2.resize(gd.intensity, new, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(gd.depth, new, interpolation=cv2.INTER_NEAREST)
            valid = cv2.resize(gd.valid.astype(np.uint8), new, interpolation=cv2.INTER_NEAREST).astype(bool)
            focal = gd.focal_px * new[0] / w
        else:
            intensity, depth, valid, focal = gd.intensity, gd.depth, gd.valid, gd.focal_px
        st = stride or max(4, size // 2)
        for y in range(0, depth.shape[0] - size + 1, st):
            for x in range(0, depth.shape[1] - size + 1, st):
                sl = (slice(y, y + size), slice(x, x + size))
                if valid[sl].mean() < min_valid:
                    continue
                for flip in (False, True) if flips else (False,):
                    gi, di, vi = intensity[sl], depth[sl], valid[sl]
                    if flip:
                        gi, di, vi = gi[:, ::-1], di[:, ::-1], vi[:, ::-1]
                    crops.append(
                        make_gd_image(np.ascontiguousarray(gi), np.ascontiguousarray(di), focal, np.ascontiguousarray(vi))
                    )
    return crops
