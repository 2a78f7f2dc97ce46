"""The views stage task: the five GD images, their cameras and a parallax preview for one card.

The synthesis itself is :mod:`pipeline.view_synthesis` (its module docstring says what the stage
does, step by step, and the artifacts' conventions).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import InvalidInputError
from pipeline.io import atomic_write, read_image, to_grey, write_json, write_npy, write_png
from pipeline.records import CardTask
from pipeline.stages.base import StageOutput, stage_task

from .geometry import MAX_RELATIVE_DEPTH_STEP, scene_centre
from .synthesis import (
    DEFAULT_VERTICAL_FOV_FOCAL,
    VIEW_NAMES,
    MissingInputError,
    SceneViews,
    ViewsStageParams,
    encode_webp,
    render_preview_frames,
    synthesise_views,
)

__all__ = ["read_map", "scene_document", "views_task"]


def read_map(data_dir: Path, relative: Any, name: str) -> np.ndarray:
    if not isinstance(relative, str) or not relative:
        raise MissingInputError(f"no {name} map recorded for this card")
    path = data_dir / relative
    if not path.is_file():
        raise MissingInputError(f"the {name} map {relative} is missing from the data folder")
    try:
        values = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise MissingInputError(f"the {name} map {relative} cannot be read: {exc}") from exc
    if values.ndim != 2 or values.dtype.kind not in "fiu":
        raise InvalidInputError(f"the {name} map must be a 2-D number array, got {values.dtype} {values.shape}")
    return values.astype(np.float64)


def scene_document(scene: SceneViews) -> dict[str, Any]:
    h, w = scene.views[0].shape
    views = []
    for name, cam in zip(VIEW_NAMES, scene.cameras):
        views.append(
            {
                "name": name,
                "image": f"{name}.png",
                "depth": f"{name}_depth.npy",
                "rotation": cam.rotation.tolist(),
                "translation": cam.translation.tolist(),
                "centre": cam.centre.tolist(),
                "focal_px": cam.focal_px,
            }
        )
    return {
        "convention": "world = v0's camera frame; cameras look down -z with y up (OpenGL); x_cam = R x_world + t; "
        "pixel (u, v) with depth D is ((u - cx) D / f, -(v - cy) D / f, -D) in its camera, "
        "cx = (width - 1) / 2, cy = (height - 1) / 2; depth in baseline units (baseline 1)",
        "width": w,
        "height": h,
        "views": views,
        "scene_centre": scene_centre(scene.views[0]).tolist(),
        "quad_radius": scene.metrics["quad_radius"],
        "depth_range": scene.metrics["depth_range"],
        "max_relative_step": MAX_RELATIVE_DEPTH_STEP,
    }


@stage_task("views")
def views_task(task: CardTask, params: ViewsStageParams) -> StageOutput:
    """The five GD images, their cameras and a parallax preview for one card (module docstring).

    ``task.inputs``: ``left`` (the rectified left view, path under ``task.data_dir``), ``depth`` or
    ``disparity_left`` (float32 npy, same size as the view), ``focal_px`` (of the rectified view;
    default the paper's 45 deg vertical field of view, 1.2071 H) and ``grade`` (``few`` / ``some`` /
    ``failure`` / None). A card graded failure is ``skipped``: it needs no views."""
    inputs = task.inputs
    if inputs.get("grade") == "failure":
        return StageOutput(status="skipped", reason="not needed: graded failure", metrics={"grade": "failure"})
    data_dir = Path(task.data_dir)
    if not inputs.get("left"):
        raise MissingInputError("no rectified left view recorded for this card; run rectify first")
    left = read_image(data_dir / inputs["left"])
    grey = to_grey(left)
    # The rectifying warp fills outside the view with black: no depth there (as the disparity stage).
    inside = (left.reshape(*left.shape[:2], -1) > 0).any(axis=2)
    if inputs.get("depth"):
        depth = read_map(data_dir, inputs["depth"], "depth")
        valid = np.isfinite(depth) & (depth > 0)
        source = "depth"
    else:
        disparity = read_map(data_dir, inputs.get("disparity_left"), "disparity")
        valid = np.isfinite(disparity) & (disparity > 1e-6)
        depth = np.where(valid, 1.0 / np.where(valid, disparity, 1.0), 0.0)  # times f below
        source = "disparity_left"
    if depth.shape != grey.shape:
        raise InvalidInputError(f"the {source} map {depth.shape[::-1]} and the left view {grey.shape[::-1]} differ in size")
    valid &= inside
    focal_in = inputs.get("focal_px")
    focal = (
        float(focal_in)
        if isinstance(focal_in, (int, float)) and math.isfinite(focal_in) and focal_in > 0
        else DEFAULT_VERTICAL_FOV_FOCAL * grey.shape[0]
    )
    if source == "disparity_left":
        depth = depth * focal  # D = f b / d with b = 1, as depth_from_disparity
        valid &= np.isfinite(depth)
    scene = synthesise_views(grey, depth, valid, focal, params)

    work_dir = Path(task.work_dir)
    artifacts: dict[str, str] = {}
    for name, view in zip(VIEW_NAMES, scene.views):
        write_png(work_dir / f"{name}.png", np.clip(np.round(view.intensity * 255.0), 0, 255).astype(np.uint8))
        write_npy(work_dir / f"{name}_depth.npy", view.depth.astype(np.float32))
        artifacts[name] = str((work_dir / f"{name}.png").relative_to(data_dir))
        artifacts[f"{name}_depth"] = str((work_dir / f"{name}_depth.npy").relative_to(data_dir))
    write_json(work_dir / "views.json", scene_document(scene))
    artifacts["scene"] = str((work_dir / "views.json").relative_to(data_dir))
    preview_clock = time.perf_counter()
    frames = render_preview_frames(scene, params.preview_side, params.preview_frames)
    payload = encode_webp(frames, params.preview_frame_ms)
    with atomic_write(work_dir / "preview.webp") as handle:
        handle.write(payload)
    artifacts["preview"] = str((work_dir / "preview.webp").relative_to(data_dir))
    metrics = {
        **scene.metrics,
        "grade": inputs.get("grade"),
        "depth_source": source,
        "focal_px_input": focal,
        "input_size": [int(grey.shape[1]), int(grey.shape[0])],
        "preview": {
            "frames": len(frames),
            "bytes": len(payload),
            "size": [int(frames[0].shape[1]), int(frames[0].shape[0])],
            "seconds": round(time.perf_counter() - preview_clock, 4),
        },
        "format": "v<i>.png 8-bit grey; v<i>_depth.npy float32 depth along the view's -z axis, baseline 1, "
        "finite and > 0 everywhere; views.json cameras; preview.webp animated",
    }
    json.dumps(metrics, allow_nan=False)  # a NaN in the record is a bug: fail here, typed, not later
    return StageOutput(status="done", metrics=metrics, artifacts=artifacts)
