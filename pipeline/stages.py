"""Per-card stage tasks: read the original, call the pure stage, write artifacts, return a record.

These are the functions workers run. Each catches everything a card can throw at it and
returns a ``failed`` record with a typed reason, so one bad card never stops a batch.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
import traceback
from pathlib import Path

import numpy as np

from . import CODE_VERSION
from .errors import PipelineError
from .filter import FilterParams, filter_card
from .crop_align import align_crops
from .disparity import DEFAULT_BACKEND, DisparityParams, depth_from_disparity, estimate_disparity, resample_512
from .io import read_image, write_jpeg, write_json, write_npy, write_png
from .records import CardTask, StageRecord, param_hash
from .rectify import RectifyParams, implied_pose, rectify_pair, warp_pair
from .split import CardSplit, crop_halves

# Halves are stored as display previews only (later stages crop the original with the
# recorded boxes): full-size PNG halves would cost ~1 MB a card, 250 GB for 250,000 cards.
PREVIEW_MAX_SIDE = 800


def filter_task(task: CardTask, params: FilterParams) -> StageRecord:
    """Split the card at its gutter and route it by SIFT good-match fraction."""
    started, clock = time.time(), time.perf_counter()
    phash = param_hash(params)
    try:
        card = read_image(task.image_path)
        split, result = filter_card(card, params)
        left, right = crop_halves(card, split)
        work_dir = Path(task.work_dir)
        artifacts = {}
        for name, half in (("left", left), ("right", right)):
            target = work_dir / f"{name}.jpg"
            write_jpeg(target, half, max_side=PREVIEW_MAX_SIDE)
            artifacts[name] = str(target.relative_to(task.data_dir))
        metrics = {
            **result.metrics(),
            "left_box": list(split.left_box),
            "right_box": list(split.right_box),
            "gutter_x": split.gutter_x,
            "split_method": split.method,
            "split_confidence": split.confidence,
            "card_size": [int(card.shape[1]), int(card.shape[0])],
        }
        return StageRecord(
            card_id=task.card_id, stage="filter", param_hash=phash, status="done", outcome=result.outcome,
            reason=result.reason, metrics=metrics, artifacts=artifacts, started_at=started,
            seconds=time.perf_counter() - clock, code_version=CODE_VERSION,
        )
    except Exception as exc:  # one bad card never stops a batch: record why, go on
        return _failed(task, "filter", phash, failure_reason(exc), started, clock)


def orient_card(card: np.ndarray, inputs: dict) -> tuple[np.ndarray, dict]:
    """Apply the judged corrections to a derived copy of the card (the original never changes).

    ``inputs["upside_down"]`` rotates the card 180 deg, ``inputs["inverted"]`` inverts its
    intensities (255 - v). A card judged upright and not inverted, or not judged at all, skips
    the step, and the returned record says so. Boxes stay in the scanned card's pixels; the
    caller turns them with the card.
    """
    applied = []
    if inputs.get("upside_down"):
        card = np.ascontiguousarray(card[::-1, ::-1])
        applied.append("rotated 180 deg")
    if inputs.get("inverted"):
        card = 255 - card
        applied.append("intensities inverted")
    if applied:
        return card, {"status": "done", "applied": applied, "source": inputs.get("orientation_source", "judgement")}
    judged = "judged upright and not inverted" if "upside_down" in inputs else "no judgement asks for a correction"
    return card, {"status": "skipped", "applied": [], "reason": f"not needed: {judged}"}


def rectify_task(task: CardTask, params: RectifyParams) -> StageRecord:
    """Rectify the card's two halves (Loop-Zhang with the paper's changes).

    ``task.inputs`` must hold the filter's ``left_box`` and ``right_box`` (card pixels). A pair
    already rectified within tolerance is recorded ``skipped`` with the reason, and its halves
    are stored unwarped so the disparity stage reads one place either way.
    """
    started, clock = time.time(), time.perf_counter()
    phash = param_hash(params)
    try:
        card, orientation = orient_card(read_image(task.image_path), task.inputs)
        boxes = task.inputs.get("left_box"), task.inputs.get("right_box")
        if boxes[0] is None or boxes[1] is None:
            raise PipelineError("no split boxes from the filter stage; run the filter first")
        if task.inputs.get("upside_down"):
            # Boxes are drawn on the card as scanned; turned 180 deg, the right photo's box
            # becomes the left one.
            height, width = card.shape[:2]
            turn = lambda b: [width - b[2], height - b[3], width - b[0], height - b[1]]  # noqa: E731
            boxes = turn(boxes[1]), turn(boxes[0])
        boxes_before = boxes
        # The paper aligns the two crops by SIFT matches and cuts both to their intersection;
        # when that cannot be done the boxes go on as given and rectification decides.
        try:
            alignment = align_crops(card, tuple(boxes[0]), tuple(boxes[1]))
            boxes = alignment.left_box, alignment.right_box
            crop_record = {"status": "done", **alignment.metrics()}
        except PipelineError as exc:
            crop_record = {"status": "failed", "reason": exc.reason(), "left_box": list(boxes[0]),
                           "right_box": list(boxes[1])}
        split = CardSplit(left_box=tuple(boxes[0]), right_box=tuple(boxes[1]), gutter_x=0, method="recorded",
                          confidence=1.0)
        left, right = (np.ascontiguousarray(half) for half in crop_halves(card, split))
        # The paper puts the principal point at the centre of the full image where known: the
        # whole left photo as split from the card, in the aligned crop's pixels.
        full = boxes_before[0]
        principal_point = ((full[0] + full[2] - 1) / 2 - boxes[0][0], (full[1] + full[3] - 1) / 2 - boxes[0][1])
        rect = rectify_pair(left, right, params, principal_point=principal_point)
        left_rect, right_rect = warp_pair(left, right, rect)
        work_dir = Path(task.work_dir)
        artifacts = {}
        for name, view in (("left", left_rect), ("right", right_rect)):
            write_png(work_dir / f"{name}.png", view)
            write_jpeg(work_dir / f"{name}_preview.jpg", view, max_side=PREVIEW_MAX_SIDE)
            artifacts[name] = str((work_dir / f"{name}.png").relative_to(task.data_dir))
            artifacts[f"{name}_preview"] = str((work_dir / f"{name}_preview.jpg").relative_to(task.data_dir))
        camera = work_dir / "rectification.json"
        view = right if rect.swapped else left  # the crop H_l maps
        write_json(camera, {
            # Read by `keystone check-homographies` (pipeline.homography_quality): "convention",
            # "pixel_origin", "width" and "height" are its keys.
            "convention": "column", "pixel_origin": "centre",
            "convention_detail": "column vectors, x' ~ H x, pixels with the origin at the top-left pixel centre; "
                                 "H_l/H_r map the cropped left/right halves (boxes in card pixels) to the rectified "
                                 "views (H_l the right half's crop when swapped); disparity d = x_left - x_right >= 0",
            "width": int(view.shape[1]), "height": int(view.shape[0]),
            "left_box": list(boxes[0]), "right_box": list(boxes[1]), **rect.metrics(),
            "implied_pose": implied_pose(rect.H_l, rect.H_r, rect.K),
        })
        artifacts["rectification"] = str(camera.relative_to(task.data_dir))
        status = "done" if rect.warp_needed else "skipped"
        reason = rect.reason if rect.warp_needed else f"not needed: {rect.reason}"
        if rect.swapped:
            reason = (reason + "; " if reason else "") + "eyes were swapped on the card: halves exchanged"
        metrics = {k: v for k, v in rect.metrics().items() if k not in ("reason",)}
        metrics["implied_pose"] = implied_pose(rect.H_l, rect.H_r, rect.K)
        metrics["orientation"] = orientation
        metrics["crop_alignment"] = crop_record
        metrics["box_source"] = task.inputs.get("box_source", "filter split")
        return StageRecord(
            card_id=task.card_id, stage="rectify", param_hash=phash, status=status, reason=reason,
            metrics=metrics, artifacts=artifacts, started_at=started, seconds=time.perf_counter() - clock,
            code_version=CODE_VERSION,
        )
    except Exception as exc:  # one bad card never stops a batch: record why, go on
        return _failed(task, "rectify", phash, failure_reason(exc), started, clock)


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


def disparity_task(task: CardTask, params: DisparityStageParams) -> StageRecord:
    """Dense disparity for both rectified views, then depth up to scale and 512 x 512 maps.

    ``task.inputs``: ``left``/``right`` (rectified views, paths under the data dir),
    ``disparity_range`` [min, max] px measured by rectification (sets the search range), and
    ``focal_px`` (K[0][0]). Disparity convention: x_right = x_left - d. Pixels outside the
    rectified views (black fill of the warp) and non-positive disparities are invalid in depth.
    """
    started, clock = time.time(), time.perf_counter()
    phash = param_hash(params)
    try:
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
        return StageRecord(
            card_id=task.card_id, stage="disparity", param_hash=phash, status="done", metrics=metrics,
            artifacts=artifacts, started_at=started, seconds=time.perf_counter() - clock, code_version=CODE_VERSION,
        )
    except Exception as exc:  # one bad card never stops a batch: record why, go on
        return _failed(task, "disparity", phash, failure_reason(exc), started, clock)


def failure_reason(exc: Exception) -> str:
    """A typed reason for a stage's record: the error's own code, or ``internal_error`` for a
    bug or an OpenCV error on a strange card."""
    if isinstance(exc, PipelineError):
        return exc.reason()
    return f"internal_error: {traceback.format_exception_only(type(exc), exc)[-1].strip()}"


def _failed(task: CardTask, stage: str, phash: str, reason: str, started: float, clock: float) -> StageRecord:
    return StageRecord(
        card_id=task.card_id, stage=stage, param_hash=phash, status="failed", reason=reason,
        started_at=started, seconds=time.perf_counter() - clock, code_version=CODE_VERSION,
    )
