"""Rectification of every real pair in ``shared/data/stereocards``, checked on the rectified pair.

Run: ``python -m benchmarks.rectify_real [--json] [--data DIR] [--crops N] [--only NAME]``.

Pairs, prepared the way the pipeline prepares them (the rectify stage in :mod:`pipeline.stages.rectify`):
every image under ``full_cards/``, ``keystone_mast_raw_scans/`` and ``cropped_pairs/jps/`` is a
card: :func:`pipeline.split.split_card` finds the two photo boxes, :func:`pipeline.crop_align.align_crops`
aligns them (on failure the boxes go on as split, as in the stage), and :func:`pipeline.rectify.rectify_pair`
gets the two crops with the stage's principal point. ``cropped_pairs/depthy_7995`` is two files,
the left and the right view, rectified as they are.

Per pair:

- ``method``: ``loop_zhang``, ``row_aligned`` or ``identity`` (already rectified), or the typed
  failure ``code``;
- ``dy_p95`` / ``dy_median`` (px): |y_l - y_r| of **fresh** SIFT matches (ratio 0.7, at most 1200 px
  per view, mapped to full resolution) found on the two rectified views (not the matches rectification used). Matches with |dy| > ``ROW_GATE`` (3) px
  are mismatches, not residual, and are left out; ``fresh_kept`` is the share kept (a
  rectification that leaves many true matches off their rows loses them here). The same with a
  10 px gate: ``dy_p95_within10``, ``fresh_kept_within10``;
- the distortion metrics of the rectification (worse view): midline angle (deg), aspect change,
  in-plane rotation (deg), kept fraction;
- ``crop_angle`` (deg): the card (each file, for the depthy pair) is cropped by 0-16 px off each
  edge (``--crops`` seeded random crops plus the 16 px crop on every edge) and rectified again;
  for each physical view the direction, in original card pixels, of the rectified row through the
  centre of the view is compared with the uncropped rectification. The largest change over views
  and crops is reported, with the largest change of the disparity range ends (px);
- ``seconds``: crop alignment and rectification of the uncropped pair (the stage's order: crop
  alignment matches at rectification's SIFT side and its matches are reused, so one SIFT pass).

Working resolution (``--work-side``, default ``RectifyParams.work_side``): the fresh matches are
found on the views as the stage stores them, at most that many px on the longer side; ``dy_*`` are
given in full-resolution px (stored px divided by ``view_scale``), ``dy_*_stored_px`` as measured.
The gates apply in stored px.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pipeline.crop_align import CropAlignParams, align_crops, matches_in_boxes
from pipeline.errors import PipelineError
from pipeline.filter import FilterParams, decode_width, filter_card
from pipeline.io import jpeg_reduction, read_image
from pipeline.rectify import (
    Rectification,
    RectifyParams,
    match_features,
    rectify_matches,
    rectify_pair,
    scale_rectification,
    stored_view_scale,
    warp_pair,
)
from pipeline.split import scale_split

ROW_GATE = 3.0  # px: fresh matches further from their row than this are mismatches (the headline figure)
DY_GATE = 10.0  # px: the looser gate, reported beside it
MAX_CROP = 16  # px off each edge
MEASURE_PARAMS = RectifyParams(max_side=1200)  # the check's own SIFT, whatever rectification's working resolution
DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass
class RealPair:
    name: str
    card: np.ndarray | None = None  # a card to split (None for a pre-split pair)
    left: np.ndarray | None = None  # pre-split views
    right: np.ndarray | None = None


@dataclass
class Prepared:
    left: np.ndarray
    right: np.ndarray
    origin_l: tuple[int, int]  # (x, y) of each view's top-left pixel in the (uncropped) source px
    origin_r: tuple[int, int]
    principal_point: tuple[float, float] | None
    matches: tuple[np.ndarray, np.ndarray, float] | None = None  # crop alignment's (pts_l, pts_r, match_scale)


def real_pairs(data: Path) -> list[RealPair]:
    root = data / "stereocards"
    pairs: list[RealPair] = []
    for folder, pattern in (("full_cards", "*.jpg"), ("keystone_mast_raw_scans", "*.jpg"), ("cropped_pairs/jps", "*.jps")):
        for path in sorted((root / folder).glob(pattern)):
            pairs.append(RealPair(f"{folder.split('/')[-1]}/{path.stem}", card=read_image(path)))
    depthy = root / "cropped_pairs" / "depthy_7995"
    if (depthy / "7995l-image.jpg").is_file():
        pairs.append(
            RealPair("depthy_7995", left=read_image(depthy / "7995l-image.jpg"), right=read_image(depthy / "7995r-image.jpg"))
        )
    return pairs


def _cut(image: np.ndarray, crop: tuple[int, int, int, int]) -> np.ndarray:
    left, top, right, bottom = crop
    h, w = image.shape[:2]
    return np.ascontiguousarray(image[top : h - bottom, left : w - right])


def prepare(pair: RealPair, crop: tuple[int, int, int, int] = (0, 0, 0, 0), params: RectifyParams = RectifyParams()) -> Prepared:
    """The two views as the rectify stage gets them, ``crop`` = (left, top, right, bottom) px cut
    off the card (off each file for a pre-split pair) first. As in the stage, crop alignment
    matches at ``params``' SIFT side and its matches are kept for rectification."""
    if pair.card is None:
        assert pair.left is not None and pair.right is not None
        return Prepared(_cut(pair.left, crop), _cut(pair.right, crop), (crop[0], crop[1]), (crop[0], crop[1]), None)
    card = _cut(pair.card, crop)
    # As the filter stage then the rectify stage: the filter splits the card and keeps its SIFT
    # matches; crop alignment and rectification reuse them (else they match at params' side).
    # The stage decodes a large JPEG scan at 1/2..1/8 (FilterParams.reduced_decode); here the
    # card is in memory, so that decode is stood in for by an area resize to the same size.
    height, width = card.shape[:2]
    factor = jpeg_reduction((width, height), (decode_width(), 1)) if FilterParams().reduced_decode else 1
    small = card
    if factor > 1:
        small = cv2.resize(card, (-(-width // factor), -(-height // factor)), interpolation=cv2.INTER_AREA)
    found, filtered = filter_card(small)
    split = scale_split(found, factor, (width, height))
    boxes_before = split.left_box, split.right_box

    def to_card(points: np.ndarray, box: tuple[int, ...]) -> np.ndarray:
        return (points + box[:2] + 0.5) * factor - 0.5

    card_matches = np.hstack([to_card(filtered.points[0], found.left_box), to_card(filtered.points[1], found.right_box)])
    matches = None
    try:
        alignment, scale = None, filtered.match_scale * factor
        box_matches = matches_in_boxes(card_matches, split.left_box, split.right_box)
        if len(box_matches[0]) >= params.min_matches:
            try:
                alignment = align_crops(card, split.left_box, split.right_box, matches=box_matches)
            except PipelineError:
                alignment = None
        if alignment is None:
            alignment = align_crops(
                card,
                split.left_box,
                split.right_box,
                CropAlignParams(ratio=params.ratio, max_side=params.max_side, max_keypoints=params.max_keypoints),
            )
            lb, rb = alignment.left_box_before, alignment.right_box_before
            scale = max(1.0, max(lb[2] - lb[0], lb[3] - lb[1], rb[2] - rb[0], rb[3] - rb[1]) / params.max_side)
        boxes = alignment.left_box, alignment.right_box
        matches = (*alignment.matches_in_crops(), scale)
    except PipelineError:
        boxes = boxes_before
    (lx0, ly0, lx1, ly1), (rx0, ry0, rx1, ry1) = boxes
    full = boxes_before[0]
    principal_point = ((full[0] + full[2] - 1) / 2 - lx0, (full[1] + full[3] - 1) / 2 - ly0)
    return Prepared(
        np.ascontiguousarray(card[ly0:ly1, lx0:lx1]),
        np.ascontiguousarray(card[ry0:ry1, rx0:rx1]),
        (lx0 + crop[0], ly0 + crop[1]),
        (rx0 + crop[0], ry0 + crop[1]),
        principal_point,
        matches,
    )


def rectify_prepared(prepared: Prepared, params: RectifyParams) -> Rectification:
    """Rectify as the stage does: from crop alignment's matches when it found them, else by
    :func:`rectify_pair` (which matches the crops itself)."""
    if prepared.matches is None:
        return rectify_pair(prepared.left, prepared.right, params, principal_point=prepared.principal_point)
    pts_l, pts_r, scale = prepared.matches
    return rectify_matches(
        pts_l,
        pts_r,
        prepared.left.shape[1::-1],
        prepared.right.shape[1::-1],
        params,
        principal_point=prepared.principal_point,
        match_scale=scale,
    )


def method_of(rect: Rectification) -> str:
    if getattr(rect, "method", None):
        return rect.method
    # Code from before Rectification.method (for before/after figures): read the reason.
    if rect.reason.startswith("already rectified"):
        return "identity"
    return "row_affine" if rect.reason.startswith("row-aligned") else "loop_zhang"


def fresh_dy(left: np.ndarray, right: np.ndarray) -> dict[str, Any]:
    """|dy| of fresh SIFT matches on a rectified pair (px). ``dy_p95``: over the matches within
    ``ROW_GATE`` px of their row (near-miss and gross mismatches out; ``fresh_kept`` says how many
    stay); ``dy_p95_within10``: the same with a ``DY_GATE`` (10 px) gate."""
    pts_l, pts_r = match_features(left, right, MEASURE_PARAMS)
    out: dict[str, Any] = {"fresh_matches": int(len(pts_l))}
    dy = np.abs(pts_l[:, 1] - pts_r[:, 1])
    for key, gate in (("", ROW_GATE), ("_within10", DY_GATE)):
        kept = dy[dy <= gate]
        out[f"fresh_kept{key}"] = round(float(len(kept) / len(dy)), 3) if len(dy) else 0.0
        out[f"dy_median{key}"] = round(float(np.median(kept)), 3) if len(kept) else None
        out[f"dy_p95{key}"] = round(float(np.percentile(kept, 95)), 3) if len(kept) >= 5 else None
    return out


def _physical(rect: Rectification, prepared: Prepared) -> list[tuple[np.ndarray, np.ndarray]]:
    """(H from source px to the rectified view, the view's centre in source px) per physical view
    (given left, given right), whatever the eye order chosen."""
    h_left, h_right = (rect.H_r, rect.H_l) if rect.swapped else (rect.H_l, rect.H_r)
    out = []
    for H, view, (ox, oy) in ((h_left, prepared.left, prepared.origin_l), (h_right, prepared.right, prepared.origin_r)):
        to_view = np.array([[1.0, 0, -ox], [0, 1.0, -oy], [0, 0, 1.0]])
        centre = np.array([ox + (view.shape[1] - 1) / 2.0, oy + (view.shape[0] - 1) / 2.0])
        out.append((H @ to_view, centre))
    return out


def row_direction(H: np.ndarray, point: np.ndarray) -> float:
    """deg in [0, 180): direction in source px of the rectified row through ``point``."""
    mapped = H @ np.array([point[0], point[1], 1.0])
    line = H.T @ np.array([0.0, mapped[2], -mapped[1]])  # preimage of the row y' = mapped y
    return math.degrees(math.atan2(-line[0], line[1])) % 180.0


def _angle_between(a: float, b: float) -> float:
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def crops(n: int, seed: int = 0) -> list[tuple[int, int, int, int]]:
    rng = np.random.default_rng(seed)
    out = [(MAX_CROP, MAX_CROP, MAX_CROP, MAX_CROP)]
    out += [tuple(int(v) for v in rng.integers(0, MAX_CROP + 1, size=4)) for _ in range(n)]
    return out  # type: ignore[return-value]


def measure(pair: RealPair, params: RectifyParams = RectifyParams(), n_crops: int = 3) -> dict[str, Any]:
    row: dict[str, Any] = {"pair": pair.name}
    clock = time.perf_counter()
    prepared = prepare(pair, params=params)
    row["view_size"] = [int(prepared.left.shape[1]), int(prepared.left.shape[0])]
    try:
        rect = rectify_prepared(prepared, params)
    except PipelineError as exc:
        row.update(method="refused", code=exc.code, reason=str(exc), seconds=round(time.perf_counter() - clock, 3))
        return row
    row["seconds"] = round(time.perf_counter() - clock, 3)  # crop alignment and rectification
    row.update(
        method=method_of(rect),
        reason=rect.reason,
        swapped=rect.swapped,
        inliers=rect.inliers,
        inlier_dy_p95=round(rect.dy_p95, 3),
        midline_angle=round(rect.midline_angle, 3),
        aspect_change=round(rect.aspect_change, 4),
        rotation=round(rect.rotation, 3),
        kept_fraction=round(rect.kept_fraction, 4),
        disparity_range=[round(v, 1) for v in rect.disparity_range],
    )
    # Fresh matches on the views as the stage stores them (at the working side), their |dy| in
    # full-resolution px (divided by the view scale) so figures compare across working sides.
    stored = scale_rectification(rect, stored_view_scale(rect.size, params.work_side))
    fresh = fresh_dy(*warp_pair(prepared.left, prepared.right, stored))
    for key in ("dy_median", "dy_p95", "dy_median_within10", "dy_p95_within10"):
        if fresh.get(key) is not None:
            fresh[f"{key}_stored_px"] = fresh[key]
            fresh[key] = round(fresh[key] / stored.view_scale, 3)
    row.update(fresh, view_scale=round(stored.view_scale, 4), stored_size=list(stored.size))
    base = [(H, c, row_direction(H, c)) for H, c in _physical(rect, prepared)]
    worst_angle, worst_range, crop_rows = 0.0, 0.0, []
    for crop in crops(n_crops):
        cropped = prepare(pair, crop, params)
        try:
            rc = rectify_prepared(cropped, params)
        except PipelineError as exc:
            crop_rows.append({"crop": list(crop), "code": exc.code})
            worst_angle = math.inf
            continue
        angle = max(_angle_between(b[2], row_direction(H, b[1])) for b, (H, _) in zip(base, _physical(rc, cropped)))
        moved = max(abs(a - b) for a, b in zip(rc.disparity_range, rect.disparity_range))
        crop_rows.append(
            {
                "crop": list(crop),
                "method": method_of(rc),
                "angle": round(angle, 3),
                "disparity_range": [round(v, 1) for v in rc.disparity_range],
            }
        )
        worst_angle, worst_range = max(worst_angle, angle), max(worst_range, moved)
    row.update(
        crop_angle=round(worst_angle, 3) if math.isfinite(worst_angle) else None,
        crop_disparity_move=round(worst_range, 1),
        crops=crop_rows,
    )
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="shared data folder (holds stereocards/)")
    parser.add_argument("--crops", type=int, default=3, help="random crops per pair besides the 16 px one")
    parser.add_argument("--only", default=None, help="only pairs whose name contains this")
    parser.add_argument(
        "--max-side",
        type=int,
        default=RectifyParams().max_side,
        help="working resolution: longer side (px) of the views SIFT matches on for rectification",
    )
    parser.add_argument(
        "--max-keypoints", type=int, default=RectifyParams().max_keypoints, help="SIFT keypoints per view for rectification"
    )
    parser.add_argument(
        "--work-side",
        default=str(RectifyParams().work_side),
        help="longer side (px) of the stored rectified views the check matches on, or 'none' (full)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    if not (args.data / "stereocards").is_dir():
        print(f"no stereocards under {args.data}", file=sys.stderr)
        return 2
    work_side = None if args.work_side.lower() in ("none", "full") else int(args.work_side)
    params = RectifyParams(max_side=args.max_side, max_keypoints=args.max_keypoints, work_side=work_side)
    rows = []
    for pair in real_pairs(args.data):
        if args.only and args.only not in pair.name:
            continue
        row = measure(pair, params, n_crops=args.crops)
        rows.append(row)
        if not args.json:
            print(
                f"{row['pair']:<58} {row['method']:<11} dy_p95 {row.get('dy_p95')!s:>6} "
                f"kept {row.get('fresh_kept')!s:>5} midline {row.get('midline_angle')!s:>7} "
                f"rot {row.get('rotation')!s:>6} crop_angle {row.get('crop_angle')!s:>6} "
                f"disp_move {row.get('crop_disparity_move')!s:>5} {row['seconds']:.2f}s "
                f"{row.get('code', '')}",
                flush=True,
            )
    if args.json:
        print(
            json.dumps(
                {
                    "max_side": args.max_side,
                    "max_keypoints": args.max_keypoints,
                    "work_side": work_side,
                    "row_gate_px": ROW_GATE,
                    "dy_gate_px": DY_GATE,
                    "max_crop_px": MAX_CROP,
                    "pairs": rows,
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
