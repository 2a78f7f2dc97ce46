"""``keystone check-homographies``: JSON shape, verdicts, per-file errors and exit status.

Invokes the click command directly: no database, no app context."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from catalogue.geometry import check_homographies_command


def _write(path: Path, H_l: np.ndarray, H_r: np.ndarray, **extra: object) -> Path:
    path.write_text(json.dumps({"H_l": H_l.tolist(), "H_r": H_r.tolist(), "convention": "column", **extra}))
    return path


def test_json_shape_and_verdicts(tmp_path: Path):
    _write(tmp_path / "04733.json", np.eye(3), np.eye(3), width=640, height=480)
    shear = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    (tmp_path / "sub").mkdir()
    _write(tmp_path / "sub" / "05000.json", shear, shear)
    result = CliRunner().invoke(check_homographies_command, [str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert set(doc) >= {"results"}
    by_id = {r["id"]: r for r in doc["results"]}
    assert set(by_id) == {"04733", "05000"}
    for r in doc["results"]:
        assert set(r) == {"id", "verdict", "metrics"}
        assert r["verdict"] in ("good", "border", "bad")
    assert by_id["04733"]["verdict"] == "good"
    assert by_id["04733"]["metrics"]["l_midline_angle_deg"] == 90.0
    assert by_id["04733"]["metrics"]["width"] == 640.0
    assert by_id["05000"]["verdict"] == "bad"
    assert by_id["05000"]["metrics"]["size_source"].startswith("assumed")


def test_bad_file_gives_error_entry_exit_1_and_others_go_on(tmp_path: Path):
    good = _write(tmp_path / "04733.json", np.eye(3), np.eye(3))
    broken = tmp_path / "04771_rectification_mats.mat"
    broken.write_bytes(b"\x00garbage")
    infinite = np.array([[1.0, 0, 0], [0, 1.0, 0], [-0.5 / 610, -0.5 / 771, 1.0]])
    far = _write(tmp_path / "04773.json", infinite, np.eye(3), width=610, height=771)
    result = CliRunner().invoke(check_homographies_command, [str(good), str(broken), str(far), "--json"])
    assert result.exit_code == 1
    doc = json.loads(result.output)  # strict JSON: no NaN / Infinity tokens
    assert "NaN" not in result.output and "Infinity" not in result.output
    by_id = {r["id"]: r for r in doc["results"]}
    assert by_id["04771"]["error"] and "verdict" not in by_id["04771"]
    assert by_id["04733"]["verdict"] == "good"
    assert by_id["04773"]["verdict"] == "bad" and by_id["04773"]["metrics"]["bounded"] is False


def test_table_output(tmp_path: Path):
    _write(tmp_path / "04733.json", np.eye(3), np.eye(3))
    result = CliRunner().invoke(check_homographies_command, [str(tmp_path / "04733.json")])
    assert result.exit_code == 0
    assert "04733" in result.output and "good" in result.output and "1 item(s): 1 good" in result.output


def test_size_option(tmp_path: Path):
    _write(tmp_path / "04733.json", np.eye(3), np.eye(3))
    result = CliRunner().invoke(check_homographies_command, [str(tmp_path), "--size", "500x400", "--json"])
    assert json.loads(result.output)["results"][0]["metrics"]["width"] == 500.0
    bad = CliRunner().invoke(check_homographies_command, [str(tmp_path), "--size", "big"])
    assert bad.exit_code == 2


def test_real_keystonedepth_files(shared_data: Path):
    root = shared_data / "keystonedepth" / "homographies"
    if not root.is_dir():
        pytest.skip("keystonedepth homographies not present")
    files = [
        str(root / "04733_rectification_mats.mat"),
        str(root / "04857_rectification_mats.mat"),
    ]
    result = CliRunner().invoke(check_homographies_command, [*files, "--json"])
    assert result.exit_code == 0, result.output
    by_id = {r["id"]: r for r in json.loads(result.output)["results"]}
    assert by_id["04733"]["verdict"] == "good"  # human label good
    assert by_id["04857"]["verdict"] == "bad"  # human label bad
    # Their projective indicator for 04857: 2.7 (left), 2.74 (right).
    assert by_id["04857"]["metrics"]["min_projective_log10"] == pytest.approx(2.74, abs=0.02)


def test_folder_scan_skips_non_homography_json(tmp_path: Path):
    _write(tmp_path / "04733.json", np.eye(3), np.eye(3))
    (tmp_path / "proj_components_r1_60.json").write_text(json.dumps({"0": ["04733", 4.6]}))
    result = CliRunner().invoke(check_homographies_command, [str(tmp_path), "--json"])
    assert result.exit_code == 0
    doc = json.loads(result.output)
    assert [r["id"] for r in doc["results"]] == ["04733"]
    assert doc["skipped"][0]["path"].endswith("proj_components_r1_60.json")
    # Named explicitly, the same file is an error.
    named = CliRunner().invoke(
        check_homographies_command,
        [str(tmp_path / "proj_components_r1_60.json"), "--json"],
    )
    assert named.exit_code == 1 and "error" in json.loads(named.output)["results"][0]


def _stage_rectification(tmp_path: Path) -> Path:
    """The rectify stage's own rectification.json for a card (Motorcycle, right photo keystoned)."""
    import cv2
    from skimage import data

    from pipeline.io import write_png
    from pipeline.records import CardTask
    from pipeline.rectify import RectifyParams
    from pipeline.stages.rectify import rectify_task

    left, right, _ = data.stereo_motorcycle()
    h, w = left.shape[:2]
    keystone = np.array([[1.0, 0.0, 0.0], [0.01, 1.0, 6.0], [5e-5, 0.0, 1.0]])
    right = cv2.warpPerspective(right, keystone, (w, h), borderMode=cv2.BORDER_REPLICATE)
    card = np.full((h + 40, 2 * w + 60, 3), 200, np.uint8)
    card[20 : 20 + h, 20 : 20 + w], card[20 : 20 + h, w + 40 : 2 * w + 40] = left, right
    write_png(tmp_path / "card.png", card)
    (tmp_path / "work").mkdir()
    task = CardTask(
        card_id=1,
        content_hash="x",
        image_path=str(tmp_path / "card.png"),
        work_dir=str(tmp_path / "work"),
        data_dir=str(tmp_path),
        inputs={"left_box": [20, 20, 20 + w, 20 + h], "right_box": [w + 40, 20, 2 * w + 40, 20 + h]},
    )
    record = rectify_task(task, RectifyParams())
    assert record.status == "done", record.reason
    return tmp_path / record.artifacts["rectification"]


def test_reads_the_rectify_stages_own_rectification_json(tmp_path: Path):
    path = _stage_rectification(tmp_path)
    document = json.loads(path.read_text())
    result = CliRunner().invoke(check_homographies_command, [str(path), "--json"])
    assert result.exit_code == 0, result.output
    (item,) = json.loads(result.output)["results"]
    assert "error" not in item and item["verdict"] in ("good", "border", "bad")
    assert item["metrics"]["size_source"] == "file"
    # The stage writes the size of the (aligned) crop H_l maps; a mild keystone is corrected with
    # little distortion.
    box = document["left_box"]
    assert (document["width"], document["height"]) == (box[2] - box[0], box[3] - box[1])
    assert 700 < document["width"] <= 741 and 460 < document["height"] <= 500
    assert item["metrics"]["max_midline_dev_deg"] < 3
    # Files written before the stage said "column" (the long convention sentence) still read,
    # with the size taken from the box and the same metrics.
    legacy = {k: v for k, v in document.items() if k not in ("width", "height", "pixel_origin", "convention_detail")}
    legacy["convention"] = (
        "column vectors, x' ~ H x, pixels with the origin at the top-left pixel centre; H_l/H_r map the cropped "
        "left/right halves (boxes in card pixels) to the rectified views; disparity d = x_left - x_right >= 0"
    )
    old = tmp_path / "legacy.json"
    old.write_text(json.dumps(legacy))
    result = CliRunner().invoke(check_homographies_command, [str(old), "--json"])
    assert result.exit_code == 0, result.output
    (legacy_item,) = json.loads(result.output)["results"]
    assert legacy_item["metrics"]["max_midline_dev_deg"] == pytest.approx(item["metrics"]["max_midline_dev_deg"])


def test_pixel_centre_origin_is_converted_and_unknown_origin_refused(tmp_path: Path):
    from pipeline import homography_quality as hq

    scale = np.diag([2.0, 2.0, 1.0])  # about the centre of the top-left pixel
    _write(tmp_path / "centre.json", scale, scale, width=100, height=50, pixel_origin="centre")
    (pair,) = hq.read_homographies(tmp_path / "centre.json")
    # x_corner' = 2 (x_corner - 0.5) + 0.5: the corner origin moves to -0.5.
    np.testing.assert_allclose(hq.apply_homography(pair.H_l, np.array([[0.0, 0.0]]))[0], [[-0.5, -0.5]])
    _write(tmp_path / "odd.json", scale, scale, pixel_origin="middle")
    result = CliRunner().invoke(check_homographies_command, [str(tmp_path / "odd.json"), "--json"])
    assert result.exit_code == 1 and "unknown pixel_origin" in result.output
