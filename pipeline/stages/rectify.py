"""The rectify stage task: apply the decided orientation, align the crops, rectify the pair."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..contracts import RectifyInputs
from ..crop_align import Box, CropAlignParams, align_crops, matches_in_boxes
from ..decided_orientation import card_orientation, is_decided
from ..errors import PipelineError
from ..io import read_image, write_jpeg, write_json, write_png
from ..records import CardTask, StageStatus
from ..rectify import (
    RectifyParams,
    implied_pose,
    rectify_matches,
    rectify_pair,
    scale_rectification,
    scaling_matrix,
    stored_view_scale,
    warp_pair,
)
from ..results import CardResults
from ..split import CardSplit, crop_halves
from .base import PREVIEW_MAX_SIDE, StageOutput, stage_task
from .filter import filter_boxes
from .orientation import photo_area_boxes
from .spec import StageDeclaration

__all__ = ["STAGE", "filter_matches", "orient_card", "oriented_boxes", "rectify_inputs", "rectify_ready", "rectify_task"]


def orient_card(card: np.ndarray, inputs: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:
    """Apply the judged corrections to a derived copy of the card (the original never changes).

    ``inputs["upside_down"]`` rotates the card 180 deg, ``inputs["inverted"]`` inverts its
    intensities (255 - v), ``inputs["swapped"]`` (after those) says the left photo is the right
    eye's: the caller exchanges the halves' boxes (:func:`oriented_boxes`). A card judged upright,
    positive and in eye order, or not judged at all, skips the step, and the returned record
    says so. Boxes stay in the scanned card's pixels; the caller turns them with the card.
    """
    applied: list[str] = []
    if inputs.get("upside_down"):
        card = np.ascontiguousarray(card[::-1, ::-1])
        applied.append("rotated 180 deg")
    if inputs.get("inverted"):
        card = 255 - card
        applied.append("intensities inverted")
    if inputs.get("swapped"):
        applied.append("halves exchanged (eyes swapped)")
    if applied:
        return card, {"status": "done", "applied": applied, "source": inputs.get("orientation_source", "judgement")}
    judged = "judged upright and not inverted" if "upside_down" in inputs else "no judgement asks for a correction"
    return card, {"status": "skipped", "applied": [], "reason": f"not needed: {judged}"}


def filter_matches(task: CardTask, card_shape: tuple[int, ...]) -> tuple[np.ndarray, float] | None:
    """The filter's good matches ``(N, 4)`` in px of the card as oriented here, and their scale
    (card px per SIFT px; under 1 when a small scan's halves were matched upsampled), or None when
    the filter left none (older runs) or they cannot be read. A card turned 180 deg turns its
    matches with it; an inverted one keeps them (same places)."""
    relative, scale = task.inputs.get("filter_matches"), task.inputs.get("filter_match_scale")
    if not isinstance(relative, str) or not isinstance(scale, (int, float)) or not (math.isfinite(scale) and scale > 0):
        return None
    try:
        matches = np.load(Path(task.data_dir) / relative, allow_pickle=False)
    except (OSError, ValueError):
        return None
    if matches.ndim != 2 or matches.shape[1] != 4 or not np.all(np.isfinite(matches)):
        return None
    matches = matches.astype(np.float64)
    if task.inputs.get("upside_down"):
        height, width = card_shape[:2]
        matches = np.column_stack(
            [width - 1 - matches[:, 0], height - 1 - matches[:, 1], width - 1 - matches[:, 2], height - 1 - matches[:, 3]]
        )
    return matches, float(scale)


def oriented_boxes(
    shape: tuple[int, int], boxes: tuple[Sequence[int], Sequence[int]], inputs: dict[str, Any]
) -> tuple[list[int], list[int]]:
    """The (left eye, right eye) boxes on the oriented card, from boxes drawn on the card as
    scanned (``shape`` = the card's (H, W)): turned 180 deg, the right photo's box becomes the
    left one; swapped, the two are exchanged after that."""
    left, right = list(boxes[0]), list(boxes[1])
    if inputs.get("upside_down"):
        height, width = shape

        def turn(b: Sequence[int]) -> list[int]:
            return [width - b[2], height - b[3], width - b[0], height - b[1]]

        left, right = turn(right), turn(left)
    if inputs.get("swapped"):
        left, right = right, left
    return left, right


def _box(values: Sequence[int], name: str) -> Box:
    """A recorded box as ``(x0, y0, x1, y1)`` card px; a typed error when it is not four values."""
    if len(values) != 4:
        raise PipelineError(f"Expected {name} as four numbers (x0, y0, x1, y1), got {list(values)!r}")
    x0, y0, x1, y1 = values
    return x0, y0, x1, y1


def _as_scanned(shape: tuple[int, int], box: Sequence[int], inputs: dict[str, Any]) -> list[int]:
    """A box on the oriented card back in the scan's pixels (turning is its own inverse)."""
    if not inputs.get("upside_down"):
        return [int(v) for v in box]
    height, width = shape
    return [int(width - box[2]), int(height - box[3]), int(width - box[0]), int(height - box[1])]


@stage_task("rectify")
def rectify_task(task: CardTask, params: RectifyParams) -> StageOutput:
    """Rectify the card's two halves (Loop-Zhang with the paper's changes).

    ``task.inputs`` must hold the filter's ``left_box`` and ``right_box`` (card pixels). A pair
    already rectified within tolerance is recorded ``skipped`` with the reason, and its halves
    are stored unwarped so the disparity stage reads one place either way.
    """
    card, orientation = orient_card(read_image(task.image_path), task.inputs)
    left_given, right_given = task.inputs.get("left_box"), task.inputs.get("right_box")
    if left_given is None or right_given is None:
        raise PipelineError("no split boxes from the filter stage; run the filter first")
    oriented = oriented_boxes(card.shape[:2], (left_given, right_given), task.inputs)
    boxes: tuple[Box, Box] = (_box(oriented[0], "left_box"), _box(oriented[1], "right_box"))
    boxes_before = boxes
    # The paper aligns the two crops by SIFT matches and cuts both to their intersection;
    # when that cannot be done the boxes go on as given and rectification decides.
    # SIFT is most of a card's cost: the filter's matches (card px) align the crops and rectify
    # the pair when there are enough of them inside the boxes; else crop alignment matches at
    # rectification's SIFT side and rectification reuses those. One SIFT pass a card either way.
    matches, source = None, "rectify"
    reused = filter_matches(task, card.shape)
    try:
        alignment = None
        if reused is not None:
            box_matches = matches_in_boxes(reused[0], boxes[0], boxes[1])
            if len(box_matches[0]) >= params.min_matches:
                try:
                    alignment = align_crops(card, boxes[0], boxes[1], matches=box_matches)
                    match_scale, source = reused[1], "filter"
                except PipelineError:
                    alignment = None
        if alignment is None:
            alignment = align_crops(
                card,
                boxes[0],
                boxes[1],
                CropAlignParams(ratio=params.ratio, max_side=params.max_side, max_keypoints=params.max_keypoints),
            )
            before = (*alignment.left_box_before, *alignment.right_box_before)
            longest = max(before[2] - before[0], before[3] - before[1], before[6] - before[4], before[7] - before[5])
            match_scale = max(1.0, longest / params.max_side)
        boxes = alignment.left_box, alignment.right_box
        crop_record = {"status": "done", **alignment.metrics(), "match_source": source}
        matches = (*alignment.matches_in_crops(), match_scale)
    except PipelineError as exc:
        crop_record = {"status": "failed", "reason": exc.reason(), "left_box": list(boxes[0]), "right_box": list(boxes[1])}
    split = CardSplit(left_box=boxes[0], right_box=boxes[1], gutter_x=0, method="recorded", confidence=1.0)
    left, right = (np.ascontiguousarray(half) for half in crop_halves(card, split))
    # The paper puts the principal point at the centre of the full image where known: the
    # whole left photo as split from the card, in the aligned crop's pixels.
    full = boxes_before[0]
    principal_point = ((full[0] + full[2] - 1) / 2 - boxes[0][0], (full[1] + full[3] - 1) / 2 - boxes[0][1])
    if matches is None:
        rect_full = rectify_pair(left, right, params, principal_point=principal_point)
        # rectify_pair matches views downscaled to params.max_side (never up)
        matched_scale = max(1.0, max(*left.shape[:2], *right.shape[:2]) / params.max_side)
    else:
        pts_l, pts_r, match_scale = matches  # match_scale: crop px per SIFT px
        matched_scale = max(1.0, match_scale)  # as rectify_matches: never under one crop pixel
        rect_full = rectify_matches(
            pts_l, pts_r, left.shape[1::-1], right.shape[1::-1], params, principal_point=principal_point, match_scale=match_scale
        )
    # The views are stored (and disparity runs) at the working resolution; the homographies keep
    # the full-resolution crops as input: H = S H_full, S the resize of the rectified frame.
    rect = scale_rectification(rect_full, stored_view_scale(rect_full.size, params.work_side))
    left_rect, right_rect = warp_pair(left, right, rect)
    work_dir = Path(task.work_dir)
    artifacts = {}
    for name, view in (("left", left_rect), ("right", right_rect)):
        write_png(work_dir / f"{name}.png", view, fast=True)  # once a card, on every card
        write_jpeg(work_dir / f"{name}_preview.jpg", view, max_side=PREVIEW_MAX_SIDE)
        artifacts[name] = str((work_dir / f"{name}.png").relative_to(task.data_dir))
        artifacts[f"{name}_preview"] = str((work_dir / f"{name}_preview.jpg").relative_to(task.data_dir))
    camera = work_dir / "rectification.json"
    scaling = scaling_matrix(rect.size[0] / rect_full.size[0], rect.size[1] / rect_full.size[1])
    view = right if rect.swapped else left  # the crop H_l maps
    write_json(
        camera,
        {
            # Read by `keystone check-homographies` (pipeline.homography_quality): "convention",
            # "pixel_origin", "width" and "height" are its keys.
            "convention": "column",
            "pixel_origin": "centre",
            "convention_detail": "column vectors, x' ~ H x, pixels with the origin at the top-left pixel centre; "
            "H_l/H_r map the full-resolution cropped left/right halves (boxes in card pixels) to "
            "the stored rectified views of size (H_l the right half's crop when swapped); "
            "disparity d = x_left - x_right >= 0 in the stored views' px",
            "working_resolution": {
                "view_scale": rect.view_scale,
                "work_side": params.work_side,
                "S": scaling.tolist(),
                "full_size": [int(v) for v in rect_full.size],
                "H_l_full": rect_full.H_l.tolist(),
                "H_r_full": rect_full.H_r.tolist(),
                "K_full": rect_full.K.tolist(),
                "convention": "stored view px = S (full-resolution rectified px), S = [[s,0,(s-1)/2],[0,s,(s-1)/2],"
                "[0,0,1]] for the top-left pixel-centre origin; H_l = S H_l_full, K = S K_full; "
                "for crops resized by S_in: H_work = S H_full S_in^-1, so H_full = S^-1 H_work S_in",
            },
            "width": int(view.shape[1]),
            "height": int(view.shape[0]),
            "left_box": list(boxes[0]),
            "right_box": list(boxes[1]),
            **rect.metrics(),
            "implied_pose": implied_pose(rect_full.H_l, rect_full.H_r, rect_full.K),
        },
    )
    artifacts["rectification"] = str(camera.relative_to(task.data_dir))
    status: StageStatus = "done" if rect.warp_needed else "skipped"
    reason = rect.reason if rect.warp_needed else f"not needed: {rect.reason}"
    if rect.swapped:
        reason = (reason + "; " if reason else "") + "eyes were swapped on the card: halves exchanged"
    metrics = {k: v for k, v in rect.metrics().items() if k not in ("reason",)}
    metrics["implied_pose"] = implied_pose(rect_full.H_l, rect_full.H_r, rect_full.K)  # the full-resolution frame's
    metrics["full_size"] = [int(v) for v in rect_full.size]
    metrics["dy_p95_full"] = float(rect_full.dy_p95)
    # px at the resolution the matches were found at (600 px halves from the filter, whatever the
    # scan's size), never finer than a pixel of the scan: where rectification's own |dy| limit
    # applies (pipeline.rectify.rectify_matches), and what the grade reads.
    metrics["dy_p95_match"] = float(rect_full.dy_p95 / matched_scale)
    metrics["orientation"] = orientation
    # What this result was computed with: a later change (crowd, curator) makes it stale.
    metrics["orientation_used"] = {flag: task.inputs.get(flag) for flag in ("upside_down", "inverted", "swapped")}
    metrics["crop_alignment"] = crop_record
    # The boxes cut, in the card's pixels as scanned (the boxes above are on the oriented card).
    metrics["scanned_boxes"] = {
        eye: _as_scanned(card.shape[:2], box, task.inputs) for eye, box in (("left_eye", boxes[0]), ("right_eye", boxes[1]))
    }
    metrics["box_source"] = task.inputs.get("box_source", "filter split")
    return StageOutput(status=status, reason=reason, metrics=metrics, artifacts=artifacts)


def rectify_inputs(card: CardResults, approved: Mapping[str, Any]) -> RectifyInputs:
    """What rectification consumes (boxes in the original card's pixels): the crowd's consensus
    boxes where approved, else the orientation step's photo areas, else the filter's split; and
    the decided orientation (:func:`pipeline.decided_orientation.card_orientation`; null flags
    while undecided)."""
    inputs = filter_boxes(card)
    inputs.update(photo_area_boxes(card))
    crop = approved.get("crop")
    if crop is not None and crop.label.get("left") and crop.label.get("right"):
        inputs.update(
            left_box=[int(round(v)) for v in crop.label["left"]],
            right_box=[int(round(v)) for v in crop.label["right"]],
            box_source=f"crowd consensus (batch {crop.batch_id})",
        )
    judge = approved.get("judge")
    if judge is not None:
        inputs["is_stereo"] = bool(judge.label.get("is_stereo", True))
    orientation = card_orientation(card, approved)
    inputs.update(
        {flag: orientation[flag] for flag in ("upside_down", "inverted", "swapped")},
        orientation_decided_by=orientation["decided_by"],
        orientation_source=orientation["source"] or "undecided",
    )
    return cast(RectifyInputs, inputs)


def rectify_ready(card: CardResults, inputs: dict[str, Any]) -> bool:
    """Passed cards unless the crowd judged them no stereo pair; review cards once judged one;
    either only once its orientation is decided (by the step, the crowd or a curator)."""
    if not inputs.get("left_box"):
        return False
    if not is_decided(inputs):
        return False
    if card.state == "review":
        return inputs.get("is_stereo") is True
    return inputs.get("is_stereo", True) is not False


# Cards the filter passed whose orientation is decided; cards in review wait for the crowd's
# judgement too, and a culled card gets nothing. Not chained: its inputs are people's decisions.
STAGE = StageDeclaration(
    name="rectify",
    position=30,
    params=RectifyParams,
    task=rectify_task,
    eligible_states=("pass", "review"),
    inputs=rectify_inputs,
    ready=rectify_ready,
)
