"""The disparity stage task: dense disparity for both rectified views, depth up to scale, 512 x 512 maps."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..contracts import DisparityInputs
from ..disparity import (
    DEFAULT_BACKEND,
    DisparityParams,
    DisparityResult,
    depth_from_disparity,
    estimate_disparity,
    resample_512,
)
from ..errors import InvalidInputError
from ..io import read_image, write_jpeg, write_npy
from ..records import CardTask
from ..rectify import photograph_mask, stored_view_scale
from ..results import CardResults
from .base import PREVIEW_MAX_SIDE, StageOutput, stage_task
from .spec import StageDeclaration

__all__ = [
    "STAGE",
    "DisparityStageParams",
    "colour_disparity",
    "disparity_at_work_side",
    "disparity_task",
    "rectified_pair",
    "upsample_map",
]


@dataclass(frozen=True)
class DisparityStageParams:
    """The disparity stage's settings: which backend, and the release resolution (px)."""

    backend: str = DEFAULT_BACKEND
    block_size: int = 3
    consistency_px: float = 1.0
    release_size: int = 512  # the paper's depth maps are 512 x 512
    range_margin_px: float = 4.0  # widen the measured disparity range: inliers miss extremes
    work_side: int | None = 800
    """px: views longer than this on their longer side are downscaled (area filter) to it for the
    backend, and the maps brought back to the views' pixels (:func:`disparity_at_work_side`);
    ``None``: full resolution. The same default as ``RectifyParams.work_side``, so views the
    rectify stage stored already fit; chosen by ``keystone bench workres``."""

    def __post_init__(self) -> None:
        if self.work_side is not None and (isinstance(self.work_side, bool) or self.work_side < 16):
            raise InvalidInputError(f"Expected work_side None or >= 16 px, got {self.work_side!r}")


def upsample_map(values: np.ndarray, size: tuple[int, int], value_scale: float = 1.0) -> np.ndarray:
    """``values`` ``(h, w)`` (NaN = unknown) resized to ``size = (W, H)`` px, times ``value_scale``.

    Bilinear on the known pixels only (normalised: known values over the resized share of known
    pixels), so a hole neither spreads NaN nor pulls its neighbours to 0; a pixel whose
    neighbourhood is under half known stays NaN. Disparity in px of the larger view is the
    working disparity times ``W / w`` (pass that as ``value_scale``).
    """
    import cv2

    values = np.asarray(values, np.float32)
    if values.ndim != 2 or min(values.shape) < 1:
        raise InvalidInputError(f"Expected a 2-D map, got shape {values.shape}")
    known = np.isfinite(values)
    filled = cv2.resize(np.where(known, values, 0.0).astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    share = cv2.resize(known.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    out = np.full(share.shape, np.nan, np.float32)
    enough = share >= 0.5
    out[enough] = filled[enough] / share[enough] * np.float32(value_scale)
    return out


def disparity_at_work_side(
    left: np.ndarray, right: np.ndarray, backend: str, params: DisparityParams, work_side: int | None
) -> tuple[DisparityResult, float]:
    """:func:`estimate_disparity` at the working resolution, maps in the given views' pixels.

    ``left``/``right``: rectified views of one size ``(H, W)``; ``params.disparity_range`` in
    their px. With the longer side over ``work_side`` both are downscaled by ``s`` (area filter),
    the range times ``s``, and the result's maps are upsampled back (:func:`upsample_map`), the
    disparities divided by ``s`` (x_right = x_left - d in the given views' px). Returns the
    result and ``s`` (1: run as given).
    """
    import cv2

    height, width = left.shape[:2]
    if right.shape[:2] != (height, width):
        raise InvalidInputError(f"Expected views of one size, got {left.shape[:2]} and {right.shape[:2]}")
    scale = stored_view_scale((width, height), work_side)
    small = (max(1, round(width * scale)), max(1, round(height * scale)))
    if scale >= 1.0 or small == (width, height):
        return estimate_disparity(left, right, backend, params), 1.0
    sx = small[0] / width

    def shrink(view: np.ndarray) -> np.ndarray:
        return cv2.resize(np.ascontiguousarray(view), small, interpolation=cv2.INTER_AREA)

    search = params.disparity_range
    work_params = replace(params, disparity_range=None if search is None else (search[0] * sx, search[1] * sx))
    result = estimate_disparity(shrink(left), shrink(right), backend, work_params)
    size = (width, height)
    confidence = upsample_map(result.confidence, size)
    return replace(
        result,
        disp_left=upsample_map(result.disp_left, size, 1.0 / sx),
        disp_right=upsample_map(result.disp_right, size, 1.0 / sx),
        confidence=np.nan_to_num(confidence, nan=0.0),
    ), sx


def colour_disparity(disp: np.ndarray, valid: np.ndarray, limits: tuple[float, float] | None = None) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB preview: turbo colours from the 1st to 99th percentile, black invalid.

    ``limits``: those two percentiles of ``disp[valid]`` (numpy float64, as ``np.percentile``
    gives them) when the caller has them already."""
    import cv2

    if not valid.any():
        return np.zeros((*disp.shape, 3), np.uint8)
    lo, hi = limits if limits is not None else np.percentile(disp[valid], [1, 99])
    scaled = np.clip((disp - lo) / max(hi - lo, 1e-6), 0, 1)
    coloured = cv2.cvtColor(cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    # Masking the contiguous RGB copy: a boolean gather from the reversed-channel view took 28 ms
    # of an 800 px map's 30.
    return np.where(valid[..., None], coloured, np.uint8(0))


@stage_task("disparity")
def disparity_task(task: CardTask, params: DisparityStageParams) -> StageOutput:
    """Dense disparity for both rectified views, then depth up to scale and 512 x 512 maps.

    ``task.inputs``: ``left``/``right`` (rectified views, paths under the data dir),
    ``disparity_range`` [min, max] px measured by rectification (sets the search range), and
    ``focal_px`` (K[0][0]). Views over ``params.work_side`` are matched at that size and the maps
    brought back to the views' pixels. Disparity convention: x_right = x_left - d. Pixels outside the
    rectified views (black fill of the warp) and non-positive disparities are invalid in depth.
    """
    data_dir = Path(task.data_dir)
    left = read_image(data_dir / task.inputs["left"])
    right = read_image(data_dir / task.inputs["right"])
    measured = task.inputs.get("disparity_range")
    search = None
    if measured is not None and all(np.isfinite(measured)):
        low, high = float(measured[0]), float(measured[1])
        margin = params.range_margin_px + 0.1 * (high - low)
        search = (low - margin, high + margin)
    result, work_scale = disparity_at_work_side(
        left,
        right,
        params.backend,
        DisparityParams(disparity_range=search, block_size=params.block_size, consistency_px=params.consistency_px),
        params.work_side,
    )
    inside = photograph_mask(left)  # the warp fills outside with black
    disp = result.disp_left
    covered = np.isfinite(disp) & inside
    focal = float(task.inputs.get("focal_px") or 1.2071 * left.shape[0])
    depth, depth_valid = depth_from_disparity(np.where(covered, disp, np.nan), focal)
    disp_512, disp_512_valid = resample_512(disp, covered, params.release_size)
    depth_512, _ = resample_512(depth, depth_valid, params.release_size)

    work_dir = Path(task.work_dir)
    maps = {
        "disparity_left": result.disp_left,
        "disparity_right": result.disp_right,
        "confidence": result.confidence,
        "depth": depth,
        "disparity_512": disp_512,
        "depth_512": depth_512,
    }
    artifacts = {}
    for name, values in maps.items():
        write_npy(work_dir / f"{name}.npy", np.asarray(values, np.float32))
        artifacts[name] = str((work_dir / f"{name}.npy").relative_to(data_dir))
    # One partition for the preview's colour limits and the metrics' percentiles (each the value
    # np.percentile gives alone): 12 instead of 20 ms on an 800 px map.
    values = disp[covered]
    limits: tuple[float, float] | None = None
    percentiles: list[float | None] = [None, None, None]
    if values.size:
        p1, p5, p50, p95, p99 = np.percentile(values, [1, 5, 50, 95, 99])
        # numpy scalars, as np.percentile returns them: a Python float would make the preview's
        # arithmetic float32 (NEP 50) and change its bytes
        limits, percentiles = (p1, p99), [float(p5), float(p50), float(p95)]
    write_jpeg(work_dir / "disparity_preview.jpg", colour_disparity(disp, covered, limits), max_side=PREVIEW_MAX_SIDE)
    confidence_grey = (np.clip(result.confidence, 0, 1) * 255).astype(np.uint8)
    write_jpeg(work_dir / "confidence_preview.jpg", confidence_grey, max_side=PREVIEW_MAX_SIDE)
    artifacts["disparity_preview"] = str((work_dir / "disparity_preview.jpg").relative_to(data_dir))
    artifacts["confidence_preview"] = str((work_dir / "confidence_preview.jpg").relative_to(data_dir))

    metrics = {
        "backend": result.backend,
        "seconds_estimate": round(result.seconds, 4),
        "coverage": round(float(covered.mean()), 4),
        "confident_fraction": round(result.confident_fraction, 4),
        "disparity_p5": percentiles[0],
        "disparity_p50": percentiles[1],
        "disparity_p95": percentiles[2],
        "depth_valid_fraction": round(float(depth_valid.mean()), 4),
        "focal_px": focal,
        "search_range": list(search) if search else None,
        "flags": list(result.flags),
        "work_scale": round(work_scale, 6),
        "work_size": [round(left.shape[1] * work_scale), round(left.shape[0] * work_scale)],
        "vertical_model": list(result.vertical_model) if result.vertical_model else None,
        "convention": "x_right = x_left - d; depth = focal_px * baseline / d with baseline 1 (up to scale)",
    }
    return StageOutput(status="done", metrics=metrics, artifacts=artifacts)


def rectified_pair(card: CardResults, approved: Mapping[str, Any]) -> DisparityInputs:
    """The rectified views, measured disparity range and focal length of the latest rectify result."""
    result = card.latest_results().get("rectify")
    if result is None or result.status not in ("done", "skipped"):
        return {}
    metrics = result.metrics
    camera = metrics.get("K") or [[None]]
    return {
        "left": result.artifacts.get("left"),
        "right": result.artifacts.get("right"),
        "disparity_range": [metrics.get("disparity_min"), metrics.get("disparity_max")],
        "focal_px": camera[0][0],
        "rectify_param_hash": result.param_hash,
    }


# Cards whose rectification is done (or was not needed); a failed one gets no run.
STAGE = StageDeclaration(
    name="disparity",
    position=40,
    params=DisparityStageParams,
    task=disparity_task,
    eligible_states=("pass", "review"),
    inputs=rectified_pair,
    requires="rectify",
    chains=True,
)
