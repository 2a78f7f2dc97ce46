"""The working resolution: homography and disparity scaling conventions, and the rectify and
disparity stages on a tiny and a huge card (the views are stored at most ``work_side`` px)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.disparity import DisparityParams
from pipeline.errors import InvalidInputError
from pipeline.io import write_png
from pipeline.records import CardTask
from pipeline.rectify import (
    RectifyParams,
    rectify_pair,
    scale_rectification,
    scaling_matrix,
    stored_view_scale,
    warp_pair,
)
from pipeline.stages.disparity import (
    DisparityStageParams,
    disparity_at_work_side,
    disparity_task,
    upsample_map,
)
from pipeline.stages.rectify import rectify_task


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    mapped = np.c_[pts, np.ones(len(pts))] @ H.T
    return mapped[:, :2] / mapped[:, 2:]


def test_scaling_matrix_follows_the_pixel_centre_convention_of_an_area_resize():
    # A ramp whose value is the x coordinate: halving it with an area filter averages pixels 2k and
    # 2k + 1, so pixel k of the small image shows x = 2k + 0.5, which S^-1 must give.
    ramp = np.tile(np.arange(64, dtype=np.float32), (8, 1))
    small = cv2.resize(ramp, (32, 4), interpolation=cv2.INTER_AREA)
    S = scaling_matrix(0.5)
    back = _apply(np.linalg.inv(S), np.c_[np.arange(32.0), np.zeros(32)])[:, 0]
    np.testing.assert_allclose(small[0], back, atol=1e-5)
    assert np.allclose(S, [[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1]])
    with pytest.raises(InvalidInputError):
        scaling_matrix(0.0)


def test_homography_scaling_round_trips():
    rng = np.random.default_rng(3)
    H = np.eye(3) + rng.normal(0, [[0.05, 0.05, 5], [0.05, 0.05, 5], [1e-5, 1e-5, 0]])
    S_in, S_out = scaling_matrix(0.31, 0.32), scaling_matrix(0.4)
    H_work = S_out @ H @ np.linalg.inv(S_in)
    np.testing.assert_allclose(np.linalg.inv(S_out) @ H_work @ S_in, H, atol=1e-12)
    # A point mapped at work scale lands where the full-resolution map, scaled, puts it.
    pts = rng.uniform(0, 1000, (20, 2))
    np.testing.assert_allclose(_apply(H_work, _apply(S_in, pts)), _apply(S_out, _apply(H, pts)), atol=1e-9)


def test_stored_view_scale_bounds_the_longer_side_and_leaves_small_views_alone():
    assert stored_view_scale((300, 200), 1000) == 1.0
    assert stored_view_scale((3000, 1500), None) == 1.0
    assert stored_view_scale((3000, 1500), 750) == pytest.approx(0.25)
    with pytest.raises(InvalidInputError):
        stored_view_scale((0, 10), 100)
    with pytest.raises(InvalidInputError):
        RectifyParams(work_side=8)
    with pytest.raises(InvalidInputError):
        DisparityStageParams(work_side=True)


def _keystoned_motorcycle(factor: float) -> tuple[np.ndarray, np.ndarray]:
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    h, w = left.shape[:2]
    keystone = np.array([[1.0, 0.0, 0.0], [0.01, 1.0, 6.0], [5e-5, 0.0, 1.0]])
    right = cv2.warpPerspective(right, keystone, (w, h), borderMode=cv2.BORDER_REPLICATE)
    if factor != 1:
        size = (round(w * factor), round(h * factor))
        left, right = (cv2.resize(v, size, interpolation=cv2.INTER_CUBIC) for v in (left, right))
    return left, right


def test_a_scaled_rectification_describes_the_downscaled_full_resolution_views():
    left, right = _keystoned_motorcycle(2.0)  # 1482 x 1000 views
    full = rectify_pair(left, right)
    small = scale_rectification(full, stored_view_scale(full.size, 600))
    assert max(small.size) == 600 and small.view_scale == pytest.approx(600 / max(full.size), rel=2e-3)
    s = small.view_scale
    assert small.K[0, 0] == pytest.approx(full.K[0, 0] * s, rel=2e-3)
    assert small.disparity_range[1] == pytest.approx(full.disparity_range[1] * s, rel=2e-3)
    assert small.dy_p95 == pytest.approx(full.dy_p95 * s, rel=2e-3)
    assert small.midline_angle == full.midline_angle and small.rotation == full.rotation
    S = scaling_matrix(small.size[0] / full.size[0], small.size[1] / full.size[1])
    np.testing.assert_allclose(small.H_l, S @ full.H_l)
    # Warping the full-resolution views at the small scale (area-downscaled first) gives the
    # full-resolution rectified views downscaled, to interpolation noise.
    big_l, _ = warp_pair(left, right, full)
    expected = cv2.resize(big_l, small.size, interpolation=cv2.INTER_AREA).astype(np.float32)
    got, _ = warp_pair(left, right, small)
    assert got.shape[1::-1] == small.size
    inner = (slice(40, -40), slice(40, -40))
    assert np.median(np.abs(got[inner].astype(np.float32) - expected[inner])) <= 2.0
    assert scale_rectification(full, 1.0) is full
    with pytest.raises(InvalidInputError):
        scale_rectification(full, 1.5)


def test_upsample_map_scales_values_and_keeps_holes_without_spreading_nan():
    disp = np.full((20, 30), 7.0, np.float32)
    disp[5:10, 5:10] = np.nan
    up = upsample_map(disp, (60, 40), 2.0)
    assert up.shape == (40, 60)
    known = np.isfinite(up)
    np.testing.assert_allclose(up[known], 14.0, rtol=1e-6)
    assert not known[14:18, 14:18].any()  # the hole's middle stays unknown
    assert known.mean() > 0.9  # and does not eat its neighbours
    with pytest.raises(InvalidInputError):
        upsample_map(np.zeros(5, np.float32), (10, 10))


def test_disparity_at_a_working_side_is_in_the_given_views_pixels():
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (600, 1300), dtype=np.uint8), (0, 0), 2.0)
    shift = 24  # px at full resolution: x_right = x_left - d
    left = np.ascontiguousarray(texture[:, :1200])
    right = np.ascontiguousarray(texture[:, shift : shift + 1200])
    result, scale = disparity_at_work_side(left, right, "sgbm", DisparityParams(disparity_range=(0.0, 40.0)), 600)
    assert scale == pytest.approx(0.5)
    assert result.disp_left.shape == left.shape
    inner = result.disp_left[50:-50, 100:-100]
    assert np.nanmedian(inner) == pytest.approx(shift, abs=0.5)
    same, one = disparity_at_work_side(left, right, "sgbm", DisparityParams(disparity_range=(0.0, 40.0)), None)
    assert one == 1.0 and np.nanmedian(same.disp_left[50:-50, 100:-100]) == pytest.approx(shift, abs=0.5)


def _card_task(tmp_path: Path, factor: float) -> CardTask:
    left, right = _keystoned_motorcycle(factor)
    h, w = left.shape[:2]
    m = max(2, round(20 * factor))
    card = np.full((h + 2 * m, 2 * w + 3 * m, 3), 200, np.uint8)
    card[m : m + h, m : m + w], card[m : m + h, w + 2 * m : 2 * w + 2 * m] = left, right
    write_png(tmp_path / "card.png", card)
    (tmp_path / "work").mkdir()
    return CardTask(
        card_id=1,
        content_hash="x",
        image_path=str(tmp_path / "card.png"),
        work_dir=str(tmp_path / "work"),
        data_dir=str(tmp_path),
        inputs={"left_box": [m, m, m + w, m + h], "right_box": [w + 2 * m, m, 2 * w + 2 * m, m + h]},
    )


@pytest.mark.parametrize("factor, work_side", [(0.25, 1000), (2.5, 600)])
def test_rectify_and_disparity_stages_store_views_at_most_the_working_side(tmp_path: Path, factor: float, work_side: int):
    """A tiny card (185 px views) keeps its size; a huge one (1850 px views) is stored at 600 px,
    its homographies still taking the full-resolution crops, its disparity in stored px."""
    from pipeline.io import read_image

    task = _card_task(tmp_path, factor)
    record = rectify_task(task, RectifyParams(work_side=work_side))
    assert record.status in ("done", "skipped"), record.reason
    metrics = record.metrics
    full_size, size = metrics["full_size"], metrics["size"]
    view = read_image(tmp_path / record.artifacts["left"])
    assert list(view.shape[1::-1]) == size
    document = json.loads((tmp_path / record.artifacts["rectification"]).read_text())
    scale = document["working_resolution"]["view_scale"]
    if factor < 1:
        assert size == full_size and scale == 1.0
    else:
        assert max(size) == work_side and scale == pytest.approx(work_side / max(full_size), rel=2e-3)
        # H_l takes the full-resolution crop (width x height in the file) to the stored view.
        S = np.array(document["working_resolution"]["S"])
        np.testing.assert_allclose(np.array(document["H_l"]), S @ np.array(document["working_resolution"]["H_l_full"]))
        assert document["width"] > 1800
        assert metrics["K"][0][0] == pytest.approx(document["working_resolution"]["K_full"][0][0] * scale, rel=2e-3)

    inputs = {
        "left": record.artifacts["left"],
        "right": record.artifacts["right"],
        "disparity_range": [metrics["disparity_min"], metrics["disparity_max"]],
        "focal_px": metrics["K"][0][0],
    }
    disparity = disparity_task(
        CardTask(1, "x", task.image_path, task.work_dir, task.data_dir, inputs), DisparityStageParams(work_side=work_side)
    )
    assert disparity.status == "done", disparity.reason
    disp = np.load(tmp_path / disparity.artifacts["disparity_left"])
    assert disp.shape == view.shape[:2]
    assert disparity.metrics["work_scale"] == 1.0  # the stored views already fit the working side
    # Motorcycle's disparities (about 9-59 px at 741 px) land in the stored views' px.
    p50 = disparity.metrics["disparity_p50"]
    expected = 30 * size[0] / 741
    assert 0.4 * expected < p50 < 2.0 * expected


def test_matches_in_boxes_takes_either_end_in_either_box():
    from pipeline.crop_align import matches_in_boxes

    card_matches = np.array(
        [
            [10.0, 20.0, 110.0, 21.0],  # left end in the left box
            [112.0, 30.0, 12.0, 31.0],  # ends given the other way round
            [10.0, 20.0, 300.0, 20.0],
        ]
    )  # right end outside both boxes
    pts_l, pts_r = matches_in_boxes(card_matches, (0, 0, 50, 50), (100, 0, 150, 50))
    np.testing.assert_allclose(pts_l, [[10, 20], [12, 31]])
    np.testing.assert_allclose(pts_r, [[10, 21], [12, 30]])


def test_the_rectify_stage_reuses_the_filters_matches(tmp_path: Path):
    """Filter then rectify, as a run does: crop alignment and rectification take the filter's
    SIFT matches (no second SIFT pass) and give the rectification the own-SIFT path gives."""
    from pipeline.filter import FilterParams
    from pipeline.stages.filter import filter_task

    task = _card_task(tmp_path, 1.0)
    filtered = filter_task(task, FilterParams())
    assert filtered.outcome == "pass" and "matches" in filtered.artifacts
    matches = np.load(tmp_path / filtered.artifacts["matches"])
    assert matches.shape == (filtered.metrics["good_matches"], 4) and matches.dtype == np.float32
    inputs = {**task.inputs, "left_box": filtered.metrics["left_box"], "right_box": filtered.metrics["right_box"]}
    own = rectify_task(CardTask(1, "x", task.image_path, task.work_dir, task.data_dir, inputs), RectifyParams())
    reused = rectify_task(
        CardTask(
            1,
            "x",
            task.image_path,
            task.work_dir,
            task.data_dir,
            {**inputs, "filter_matches": filtered.artifacts["matches"], "filter_match_scale": filtered.metrics["match_scale"]},
        ),
        RectifyParams(),
    )
    assert own.status == reused.status == "done", (own.reason, reused.reason)
    assert own.metrics["crop_alignment"]["match_source"] == "rectify"
    assert reused.metrics["crop_alignment"]["match_source"] == "filter"
    assert reused.metrics["dy_p95"] < 1.5
    assert abs(reused.metrics["disparity_max"] - own.metrics["disparity_max"]) < 3
    # A card judged upside down turns the filter's matches with it: still found in the turned boxes.
    flipped = rectify_task(
        CardTask(
            1,
            "x",
            task.image_path,
            task.work_dir,
            task.data_dir,
            {
                **inputs,
                "upside_down": True,
                "filter_matches": filtered.artifacts["matches"],
                "filter_match_scale": filtered.metrics["match_scale"],
            },
        ),
        RectifyParams(),
    )
    assert flipped.status == "done" and flipped.metrics["crop_alignment"]["match_source"] == "filter"


def test_the_filter_decodes_a_large_jpeg_at_half_size_and_records_full_card_pixels(tmp_path: Path):
    """A 3,800 px JPEG card: the filter decodes it at 1/2 (each half still over 1.125 x the SIFT
    side), and its boxes, gutter and matches are in the full card's pixels, where the full decode
    puts them; rectification from either set of matches agrees."""
    from PIL import Image

    from pipeline.filter import FilterParams, decode_width
    from pipeline.stages.filter import filter_task

    task = _card_task(tmp_path, 2.5)
    card = np.asarray(Image.open(task.image_path).convert("RGB"))
    Image.fromarray(card).save(tmp_path / "card.jpg", quality=92)
    task = CardTask(1, "x", str(tmp_path / "card.jpg"), task.work_dir, task.data_dir, task.inputs)
    height, width = card.shape[:2]
    assert width // 2 >= decode_width() > width // 4

    records = {}
    for reduced in (True, False):
        folder = tmp_path / f"work-{reduced}"
        folder.mkdir()
        one = CardTask(1, "x", task.image_path, str(folder), task.data_dir, task.inputs)
        records[reduced] = filter_task(one, FilterParams(reduced_decode=reduced))
    small, full = records[True], records[False]
    assert small.outcome == full.outcome == "pass", (small.reason, full.reason)
    assert (small.metrics["decode_factor"], full.metrics["decode_factor"]) == (2, 1)
    assert small.metrics["card_size"] == full.metrics["card_size"] == [width, height]
    assert small.metrics["left_size"] == full.metrics["left_size"]  # SIFT sees a copy of the same size
    assert small.metrics["match_scale"] == pytest.approx(full.metrics["match_scale"], rel=0.01)
    for name in ("left_box", "right_box"):
        assert np.abs(np.subtract(small.metrics[name], full.metrics[name])).max() <= 8, name
    assert abs(small.metrics["gutter_x"] - full.metrics["gutter_x"]) <= 8
    matches = {key: np.load(tmp_path / record.artifacts["matches"]) for key, record in records.items()}
    for key in matches:  # in card px: inside the card, the right end in the right half
        assert matches[key][:, [0, 2]].max() < width and matches[key][:, 0].max() < records[key].metrics["gutter_x"]
    # The two decodes give SIFT slightly different pictures, so different keypoints: the median
    # offset between the photos agrees within one SIFT pixel (match_scale card px) vertically and
    # two horizontally, where it also depends on which depths the keypoints sample.
    offsets = {key: np.median(m[:, 2:] - m[:, :2], axis=0) for key, m in matches.items()}
    sift_px = full.metrics["match_scale"]
    assert abs(offsets[True][1] - offsets[False][1]) <= sift_px
    assert abs(offsets[True][0] - offsets[False][0]) <= 2 * sift_px

    rectified = {}
    for key, record in records.items():
        inputs = {
            "left_box": record.metrics["left_box"],
            "right_box": record.metrics["right_box"],
            "filter_matches": record.artifacts["matches"],
            "filter_match_scale": record.metrics["match_scale"],
        }
        folder = tmp_path / f"rectify-{key}"
        folder.mkdir()
        rectified[key] = rectify_task(CardTask(1, "x", task.image_path, str(folder), task.data_dir, inputs), RectifyParams())
        assert rectified[key].status == "done", rectified[key].reason
        assert rectified[key].metrics["crop_alignment"]["match_source"] == "filter"
    assert rectified[True].metrics["dy_p95"] < 1.5
    assert abs(rectified[True].metrics["disparity_max"] - rectified[False].metrics["disparity_max"]) < 3
