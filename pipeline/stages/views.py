"""The views stage task: the five GD images, their cameras and a parallax preview for one card.

The synthesis itself is :mod:`pipeline.view_synthesis` (its module docstring says what the stage
does, step by step, and the artifacts' conventions).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..contracts import ViewsInputs
from ..errors import InvalidInputError
from ..io import atomic_write, encode_jpeg, read_image, to_grey, write_json, write_npy
from ..records import CardTask
from ..results import CardResults
from ..view_synthesis import (
    DEFAULT_VERTICAL_FOV_FOCAL,
    VIEW_NAMES,
    MissingInputError,
    SceneViews,
    ViewsStageParams,
    encode_webp,
    render_preview_frames,
    synthesise_views,
)
from ..views import MAX_RELATIVE_DEPTH_STEP
from .base import StageOutput, stage_task
from .spec import StageDeclaration, has_inputs

__all__ = [
    "STAGE",
    "MESH_MAX_VERTICES",
    "encode_view_png",
    "WEB_JPEG_QUALITY",
    "is_colour",
    "mesh_grid",
    "read_map",
    "scene_document",
    "viewer_mesh_png",
    "views_inputs",
    "views_task",
]

# What the browser viewer downloads per view (app/static/viewer.js): the picture as a JPEG, and the
# depth as a 16-bit quantised inverse depth on the viewer's mesh grid, packed into an 8-bit RGB PNG
# (a browser decodes 16-bit PNGs to 8 bits). Measured on 5 real cards at 512 px: 0.3-0.5 MB a card
# in all, against 5.2 MB for the PNGs and float32 .npy maps the viewer read before.
WEB_JPEG_QUALITY = 88
MESH_MAX_VERTICES = 65000  # WebGL 1: one 16-bit index buffer per mesh
COLOUR_SPREAD = 8  # a scan is colour when the 99th percentile of max - min over RGB exceeds this


def is_colour(image: np.ndarray, inside: np.ndarray) -> bool:
    """Whether an RGB ``image`` (H, W, 3) uint8 carries colour over the pixels ``inside`` (H, W) bool:
    a grey scan stored as RGB (JPEG noise of 1-3 levels) is grey; a sepia or tinted card is colour."""
    if image.ndim != 3 or not inside.any():
        return False
    stride = max(1, int(math.sqrt(image.shape[0] * image.shape[1] / 250_000)))  # ~250k samples suffice
    sample, kept = image[::stride, ::stride], inside[::stride, ::stride]
    if not kept.any():
        return False
    # max - min over the channels from their planes (a reduction over a last axis of 3 costs ten
    # times more), and the percentile from the counts of the 256 possible spreads: numpy's linear
    # rule, order statistics k and k + 1 at k + frac = 0.99 (n - 1)
    r, g, b = (sample[..., k] for k in range(3))
    spread = np.maximum(np.maximum(r, g), b) - np.minimum(np.minimum(r, g), b)
    counts = np.cumsum(np.bincount(spread[kept], minlength=256))
    rank = 0.99 * (int(counts[-1]) - 1)
    low = int(np.searchsorted(counts, math.floor(rank), side="right"))
    high = int(np.searchsorted(counts, min(math.floor(rank) + 1, int(counts[-1]) - 1), side="right"))
    return low + (high - low) * (rank - math.floor(rank)) > COLOUR_SPREAD


def mesh_grid(width: int, height: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The viewer's mesh grid: ``(step, xs, ys)``, a vertex every ``step`` px (at most
    :data:`MESH_MAX_VERTICES` vertices), the last column and row always included."""
    step = max(1, math.ceil(math.sqrt(width * height / MESH_MAX_VERTICES)))
    xs = np.unique(np.append(np.arange(0, width - 1, step), width - 1))
    ys = np.unique(np.append(np.arange(0, height - 1, step), height - 1))
    while len(xs) * len(ys) > MESH_MAX_VERTICES:  # the appended last row/column can tip it over
        step += 1
        xs = np.unique(np.append(np.arange(0, width - 1, step), width - 1))
        ys = np.unique(np.append(np.arange(0, height - 1, step), height - 1))
    return step, xs, ys


def encode_view_png(pixels: np.ndarray) -> bytes:
    """A view's PNG (grey (H, W) or RGB (H, W, 3) uint8, lossless): every row Paeth-filtered and
    Huffman-coded without string matching. Measured on five 512 px colour views of a JPS card: 9 %
    larger than Pillow's adaptive filters at zlib level 3, and a third of the CPU time (0.05 s
    against 0.13 s a card)."""
    import cv2

    picture = pixels[..., ::-1] if pixels.ndim == 3 else pixels  # OpenCV writes BGR
    flags = [
        cv2.IMWRITE_PNG_COMPRESSION, 1,
        cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
        cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_PAETH,
    ]  # fmt: skip
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(picture), flags)
    if not ok:
        raise InvalidInputError(f"OpenCV could not encode a {pixels.dtype} {pixels.shape} view as PNG")
    return encoded.tobytes()


def viewer_mesh_png(depth: np.ndarray, xs: np.ndarray, ys: np.ndarray, inverse_range: tuple[float, float]) -> bytes:
    """A view's depth (H, W) > 0 sampled on the mesh grid as quantised inverse depth
    ``q = round(65535 (1/D - lo) / (hi - lo))``, ``(lo, hi) = inverse_range``, packed into an
    8-bit RGB PNG: R = q // 256, G = q % 256, B = 0. Decoded, 1/D is exact to (hi - lo) / 131070."""
    lo, hi = inverse_range
    inverse = 1.0 / depth[np.ix_(ys, xs)].astype(np.float64)
    q = np.clip(np.round((inverse - lo) / (hi - lo) * 65535.0), 0, 65535).astype(np.uint16)
    rgb = np.zeros((*q.shape, 3), np.uint8)
    rgb[..., 0], rgb[..., 1] = q >> 8, q & 255
    # 6 % smaller than Pillow's at zlib level 1, and 2.3 times faster (five 257 x 252 meshes)
    return encode_view_png(rgb)


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


def scene_document(scene: SceneViews, mesh: dict[str, Any] | None = None) -> dict[str, Any]:
    """views.json: the cameras and conventions (and ``mesh``: the viewer's grid and encoding)."""
    h, w = scene.views[0].shape
    views = []
    for name, cam in zip(VIEW_NAMES, scene.cameras):
        views.append(
            {
                "name": name,
                "image": f"{name}.png",
                "depth": f"{name}_depth.npy",
                "web_image": f"{name}.jpg",
                "mesh": f"{name}_mesh.png",
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
        "scene_centre": scene.centre.tolist(),
        "quad_radius": scene.metrics["quad_radius"],
        "depth_range": scene.metrics["depth_range"],
        "max_relative_step": MAX_RELATIVE_DEPTH_STEP,
        "max_stretch_px": scene.metrics.get("max_stretch_px"),
        "colour": scene.views[0].intensity.ndim == 3,
        "mesh": mesh,
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
    channels = left.reshape(*left.shape[:2], -1)
    inside: np.ndarray = channels[..., 0] > 0
    for k in range(1, channels.shape[2]):  # plane by plane: any() over a last axis of 3 is slow
        inside |= channels[..., k] > 0
    colour = is_colour(left, inside)
    picture = left if colour else grey
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
    scene = synthesise_views(picture, depth, valid, focal, params)

    work_dir = Path(task.work_dir)
    artifacts: dict[str, str] = {}
    h, w = scene.views[0].shape
    step, xs, ys = mesh_grid(w, h)
    lo_depth, hi_depth = scene.metrics["depth_range"]
    inverse_range = (1.0 / hi_depth, 1.0 / lo_depth if hi_depth > lo_depth else 2.0 / lo_depth)
    viewer_bytes = 0
    for name, view in zip(VIEW_NAMES, scene.views):
        levels = view.intensity * 255.0  # rounded and clipped in place: the same levels, fewer copies
        np.rint(levels, out=levels)
        pixels = np.clip(levels, 0, 255, out=levels).astype(np.uint8)
        with atomic_write(work_dir / f"{name}.png") as handle:
            handle.write(encode_view_png(pixels))
        write_npy(work_dir / f"{name}_depth.npy", np.asarray(view.depth, np.float32))
        web = {
            "web": (f"{name}.jpg", encode_jpeg(pixels, quality=WEB_JPEG_QUALITY)),
            "mesh": (f"{name}_mesh.png", viewer_mesh_png(view.depth, xs, ys, inverse_range)),
        }
        for kind, (file_name, payload) in web.items():
            with atomic_write(work_dir / file_name) as handle:
                handle.write(payload)
            artifacts[f"{name}_{kind}"] = str((work_dir / file_name).relative_to(data_dir))
            viewer_bytes += len(payload)
        artifacts[name] = str((work_dir / f"{name}.png").relative_to(data_dir))
        artifacts[f"{name}_depth"] = str((work_dir / f"{name}_depth.npy").relative_to(data_dir))
    mesh = {
        "step": step,
        "columns": len(xs),
        "rows": len(ys),
        "inverse_depth_range": list(inverse_range),
        "encoding": "v<i>_mesh.png: 8-bit RGB on the grid x = 0, step, .. and the last column (rows "
        "alike); q = 256 R + G, 1/D = lo + q / 65535 (hi - lo), (lo, hi) = inverse_depth_range",
    }
    write_json(work_dir / "views.json", scene_document(scene, mesh))
    artifacts["scene"] = str((work_dir / "views.json").relative_to(data_dir))
    preview_clock = time.perf_counter()
    frames = render_preview_frames(scene, params.preview_side, params.preview_frames, params.max_stretch_px)
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
        "colour": colour,
        "viewer_bytes": viewer_bytes,
        "format": "v<i>.png 8-bit grey, or RGB where the rectified view is colour; v<i>_depth.npy float32 depth "
        "along the view's -z axis, baseline 1, finite and > 0 everywhere; views.json cameras; "
        "v<i>.jpg and v<i>_mesh.png (quantised inverse depth) for the viewer; preview.webp animated",
    }
    json.dumps(metrics, allow_nan=False)  # a NaN in the record is a bug: fail here, typed, not later
    return StageOutput(status="done", metrics=metrics, artifacts=artifacts)


def views_inputs(card: CardResults, approved: Mapping[str, Any]) -> ViewsInputs:
    """What view synthesis needs: the rectified left view, its disparity, the focal length, and
    the grade (a card graded failure gets no views)."""
    latest = card.latest_results()
    rectify, disparity, grade = latest.get("rectify"), latest.get("disparity"), latest.get("grade")
    if rectify is None or disparity is None or disparity.status != "done" or grade is None:
        return {}
    return {
        "left": rectify.artifacts.get("left"),
        "disparity_left": disparity.artifacts.get("disparity_left"),
        "focal_px": disparity.metrics.get("focal_px"),
        "grade": grade.outcome if grade.status == "done" else None,
        "grade_param_hash": grade.param_hash,
    }


# Optional per scene (not in `keystone run`'s default stages): the five GD images and a parallax
# preview; a failure gets none. A trained inpainting checkpoint comes from the app's config.
STAGE = StageDeclaration(
    name="views",
    position=60,
    params=ViewsStageParams,
    task=views_task,
    eligible_states=("pass", "review"),
    inputs=views_inputs,
    requires="grade",
    ready=has_inputs,
    chains=True,
    keystone_run="on_request",
    params_from_config={"checkpoint": "KEYSTONE_INPAINT_CHECKPOINT"},
)
