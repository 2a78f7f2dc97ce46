"""Contracts between the layers: image arrays checked at the door of every stage, and the typed
shape of the stage metrics and inputs that cross from the pipeline to the run driver and back."""

from __future__ import annotations

from typing import Any, TypedDict

import numpy as np

from .errors import InvalidInputError


def check_image(image: object, name: str = "image", min_width: int = 1, min_height: int = 1) -> np.ndarray:
    """Raise :class:`InvalidInputError` unless ``image`` is a uint8 ``(H, W)`` or ``(H, W, 3)``
    array of at least ``min_width`` x ``min_height`` pixels; returns it for chaining."""
    if not isinstance(image, np.ndarray):
        raise InvalidInputError(f"Expected {name} as a numpy array, got {type(image).__name__}")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise InvalidInputError(f"Expected {name} with shape (H, W) or (H, W, 3), got {image.shape}")
    if image.dtype != np.uint8:
        raise InvalidInputError(f"Expected {name} with dtype uint8, got {image.dtype}")
    height, width = image.shape[:2]
    if width < min_width or height < min_height:
        raise InvalidInputError(f"Expected {name} of at least {min_width}x{min_height} px (W x H), got {width}x{height}")
    return image


# --------------------------------------------------------------------------- stage records
# What crosses from a stage, through ``stage_results.metrics`` (JSON) in the database, to the
# run driver's input builders (``runs.loop``) and on into the next stage's ``CardTask.inputs``.
# TypedDicts, so the JSON stays plain dicts at run time (behaviour unchanged, a record from an
# older version still loads) while a type checker sees which keys each side relies on.
# ``total=False``: a record written by an older stage version may lack a key; readers use .get.

Box = list[int]  # (x0, y0, x1, y1) in card pixels, x1/y1 exclusive, as pipeline.split


class FilterMetrics(TypedDict, total=False):
    """``metrics`` of a ``filter`` record: :meth:`pipeline.filter.FilterResult.metrics` plus the split."""

    outcome: str  # "pass" / "review" / "culled"
    good_matches: int
    keypoints_left: int
    keypoints_right: int
    denominator: str  # which keypoint count good_match_fraction divides by
    good_match_fraction: float
    consistent_matches: int
    ratio: float
    cull_fraction: float
    review_fraction: float
    min_good_matches: int
    max_side: int
    max_keypoints: int
    check_geometry: bool
    row_tolerance: float
    disparity_tolerance: float
    min_consistent_share: float
    left_size: list[int]  # (W, H) of the half as matched
    right_size: list[int]
    detect_seconds: float
    match_seconds: float
    left_box: Box
    right_box: Box
    gutter_x: int
    split_method: str
    split_confidence: float
    card_size: list[int]  # (W, H)
    match_scale: float  # card px per px of the image the filter matched on (its saved matches are in card px)
    decode_factor: int  # the card was decoded at 1 / this (1, 2, 4, 8; FilterParams.reduced_decode); boxes stay in card px


class RectifyMetrics(TypedDict, total=False):
    """``metrics`` of a ``rectify`` record: :meth:`pipeline.rectify.Rectification.metrics` (less
    ``reason``, which is the record's own) plus the pose, the orientation and crop steps."""

    H_l: list[list[float]]  # 3x3 homography of the left view, row = row of H
    H_r: list[list[float]]
    size: list[int]  # (W, H) of the rectified views as stored (at most RectifyParams.work_side)
    full_size: list[int]  # (W, H) the rectified views would have at the crops' full resolution
    view_scale: float  # stored view px per full-resolution px (<= 1); H, K, dy are in stored px
    dy_p95_full: float  # |dy| p95 in full-resolution px
    dy_p95_match: float  # |dy| p95 in px of the images matched on (600 px halves), never under a scan px
    K: list[list[float]]  # 3x3 camera matrix; K[0][0] the focal length in px
    R: list[list[float]]
    t: list[float]
    disparity_min: float  # px, measured on the inliers after rectification
    disparity_max: float
    dy_median: float  # px, residual vertical disparity
    dy_p95: float
    midline_angle: float  # deg
    aspect_change: float
    shear: float
    kept_fraction: float
    matches: int
    inliers: int
    swapped: bool
    warp_needed: bool
    seconds: float
    rotation: float  # deg
    method: str
    implied_pose: dict[str, Any]
    orientation: dict[str, Any]  # the judged corrections applied (rotate 180, invert)
    crop_alignment: dict[str, Any]
    box_source: str  # "filter split (...)", "photo area (...)" or "crowd consensus (batch N)"
    orientation_used: dict[str, Any]  # {"upside_down", "inverted", "swapped"}: the inputs it ran with
    scanned_boxes: dict[str, Any]  # {"left_eye", "right_eye"}: the boxes cut, in the scan's pixels


class DisparityMetrics(TypedDict, total=False):
    """``metrics`` of a ``disparity`` record (:func:`pipeline.stages.disparity.disparity_task`)."""

    backend: str
    seconds_estimate: float
    work_scale: float  # matched px per stored view px (<= 1); the maps are brought back to view px
    work_size: list[int]  # (W, H) the pair was matched at
    coverage: float  # share of left-view pixels with a disparity
    confident_fraction: float
    disparity_p5: float | None  # px over covered pixels; None when none is covered
    disparity_p50: float | None
    disparity_p95: float | None
    depth_valid_fraction: float
    focal_px: float
    search_range: list[float] | None
    flags: list[str]
    vertical_model: list[float] | None
    convention: str  # "x_right = x_left - d; depth = focal_px * baseline / d ..."


class RectifyInputs(TypedDict, total=False):
    """``CardTask.inputs`` of the rectify stage (``pipeline.stages.rectify.rectify_inputs``)."""

    left_box: Box
    right_box: Box
    box_source: str
    is_stereo: bool
    upside_down: bool | None  # pipeline.decided_orientation: null while undecided (the card is then not ready)
    inverted: bool | None
    swapped: bool | None
    orientation_decided_by: str | None  # "auto" | "crowd" | "curator"
    orientation_source: str
    filter_matches: str | None  # the filter's good matches (.npy under the data dir, card px), reused by rectify
    filter_match_scale: float | None  # the filter's match_scale


class DisparityInputs(TypedDict, total=False):
    """``CardTask.inputs`` of the disparity stage (``pipeline.stages.disparity.rectified_pair``); paths under the data dir."""

    left: str | None
    right: str | None
    disparity_range: list[float | None]  # [RectifyMetrics.disparity_min, disparity_max]
    focal_px: float | None  # RectifyMetrics.K[0][0]
    rectify_param_hash: str


class GradeInputMetrics(TypedDict, total=False):
    """The earlier stages' metrics the grader reads (``GradeInputs.metrics``), by stage."""

    filter: FilterMetrics
    rectify: RectifyMetrics
    disparity: DisparityMetrics


class GradeInputs(TypedDict, total=False):
    """``CardTask.inputs`` of the grade stage (``pipeline.stages.grade.grade_inputs``); paths under the data dir."""

    left: str | None
    right: str | None
    disparity_left: str | None
    disparity_right: str | None
    confidence: str | None
    metrics: GradeInputMetrics
    disparity_param_hash: str


class ViewsInputs(TypedDict, total=False):
    """``CardTask.inputs`` of the views stage (``pipeline.stages.views.views_inputs``); paths under the data dir."""

    left: str | None
    disparity_left: str | None
    depth: str | None
    focal_px: float | None  # DisparityMetrics.focal_px
    grade: str | None  # the grade's outcome; "failure" gets no views
    grade_param_hash: str
