"""The disparity stage task: dense disparity for both rectified views, depth up to scale, 512 x 512 maps."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..disparity import DEFAULT_BACKEND, DisparityParams, depth_from_disparity, estimate_disparity, resample_512
from ..io import read_image, write_jpeg, write_npy
from ..records import CardTask
from .base import PREVIEW_MAX_SIDE, StageOutput, stage_task

__all__ = ["DisparityStageParams", "colour_disparity", "disparity_task"]


@dataclass(frozen=True)
class DisparityStageParams:
    """The disparity stage's settings: which backend, and the release resolution (px)."""

    backend: str = DEFAULT_BACKEND
    block_size: int = 3
    consistency_px: float = 1.0
    release_size: int = 512  # the paper's depth maps are 512 x 512
    range_margin_px: float = 4.0  # widen the measured disparity range: inliers miss extremes


def colour_disparity(disp: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB preview: turbo colours from the 1st to 99th percentile, black invalid."""
    import cv2

    picture = np.zeros((*disp.shape, 3), np.uint8)
    if not valid.any():
        return picture
    lo, hi = np.percentile(disp[valid], [1, 99])
    scaled = np.clip((disp - lo) / max(hi - lo, 1e-6), 0, 1)
    coloured = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    picture[valid] = coloured[valid]
    return picture


@stage_task("disparity")
def disparity_task(task: CardTask, params: DisparityStageParams) -> StageOutput:
    """Dense disparity for both rectified views, then depth up to scale and 512 x 512 maps.

    ``task.inputs``: ``left``/``right`` (rectified views, paths under the data dir),
    ``disparity_range`` [min, max] px measured by rectification (sets the search range), and
    ``focal_px`` (K[0][0]). Disparity convention: x_right = x_left - d. Pixels outside the
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
    result = estimate_disparity(
        left, right, params.backend,
        DisparityParams(disparity_range=search, block_size=params.block_size, consistency_px=params.consistency_px),
    )
    inside = (left.reshape(*left.shape[:2], -1) > 0).any(axis=2)  # the warp fills outside with black
    disp = result.disp_left
    covered = np.isfinite(disp) & inside
    focal = float(task.inputs.get("focal_px") or 1.2071 * left.shape[0])
    depth, depth_valid = depth_from_disparity(np.where(covered, disp, np.nan), focal)
    disp_512, disp_512_valid = resample_512(disp, covered, params.release_size)
    depth_512, _ = resample_512(depth, depth_valid, params.release_size)

    work_dir = Path(task.work_dir)
    maps = {
        "disparity_left": result.disp_left, "disparity_right": result.disp_right,
        "confidence": result.confidence, "depth": depth,
        "disparity_512": disp_512, "depth_512": depth_512,
    }
    artifacts = {}
    for name, values in maps.items():
        write_npy(work_dir / f"{name}.npy", np.asarray(values, np.float32))
        artifacts[name] = str((work_dir / f"{name}.npy").relative_to(data_dir))
    write_jpeg(work_dir / "disparity_preview.jpg", colour_disparity(disp, covered), max_side=PREVIEW_MAX_SIDE)
    confidence_grey = (np.clip(result.confidence, 0, 1) * 255).astype(np.uint8)
    write_jpeg(work_dir / "confidence_preview.jpg", confidence_grey, max_side=PREVIEW_MAX_SIDE)
    artifacts["disparity_preview"] = str((work_dir / "disparity_preview.jpg").relative_to(data_dir))
    artifacts["confidence_preview"] = str((work_dir / "confidence_preview.jpg").relative_to(data_dir))

    values = disp[covered]
    percentiles = np.percentile(values, [5, 50, 95]).tolist() if values.size else [None, None, None]
    metrics = {
        "backend": result.backend, "seconds_estimate": round(result.seconds, 4),
        "coverage": round(float(covered.mean()), 4), "confident_fraction": round(result.confident_fraction, 4),
        "disparity_p5": percentiles[0], "disparity_p50": percentiles[1], "disparity_p95": percentiles[2],
        "depth_valid_fraction": round(float(depth_valid.mean()), 4), "focal_px": focal,
        "search_range": list(search) if search else None, "flags": list(result.flags),
        "vertical_model": list(result.vertical_model) if result.vertical_model else None,
        "convention": "x_right = x_left - d; depth = focal_px * baseline / d with baseline 1 (up to scale)",
    }
    return StageOutput(status="done", metrics=metrics, artifacts=artifacts)
