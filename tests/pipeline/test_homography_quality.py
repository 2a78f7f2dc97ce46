"""Third-party rectifying homographies: conventions, distortion metrics, the calibrated verdict."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline import homography_quality as hq

W, H = 600.0, 800.0


def test_row_vector_translation_maps_point_like_matlab():
    # Row convention: translation (tx, ty) sits in the last row; (u, v, 1) @ H_row.
    H_row = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-215.0, 40.0, 1.0]])
    expect = np.array([10.0, 20.0, 1.0]) @ H_row
    H_col = hq.row_to_column(H_row)
    xy, w = hq.apply_homography(H_col, [[10.0, 20.0]])
    assert xy[0].tolist() == [-205.0, 60.0] == expect[:2].tolist()
    assert w[0] == 1.0
    assert H_col[0, 2] == -215.0 and H_col[1, 2] == 40.0


def test_row_vector_projective_entries_are_transposed():
    H_row = np.array([[1.0, 0.0, 2e-4], [0.0, 1.0, 0.0], [5.0, 0.0, 1.0]])
    p = np.array([100.0, 50.0, 1.0]) @ H_row
    xy, _ = hq.apply_homography(hq.row_to_column(H_row), [[100.0, 50.0]])
    np.testing.assert_allclose(xy[0], p[:2] / p[2])
    assert xy[0, 0] == pytest.approx(105.0 / 1.02)


def test_identity_is_good_with_right_angle_midlines():
    m = hq.pair_metrics(np.eye(3), np.eye(3), W, H)
    assert m["l_midline_angle_deg"] == 90.0 and m["r_midline_angle_deg"] == 90.0
    assert m["max_corner_disp"] == 0.0 and m["max_aspect_dev"] == 0.0 and m["l_area_change"] == 1.0
    assert m["bounded"] is True and m["lr_row_spread"] == 0.0 and m["lr_vscale_ratio"] == 1.0
    assert hq.SHIPPED_MODEL.predict(m) == "good"


def test_pure_translation_and_uniform_scale_are_not_distortion():
    Hs = np.array([[1.5, 0, -300.0], [0, 1.5, 80.0], [0, 0, 1.0]])
    m = hq.pair_metrics(Hs, Hs, W, H)
    assert m["max_corner_disp"] == pytest.approx(0.0, abs=1e-12)
    assert m["l_area_change"] == pytest.approx(2.25)
    assert m["l_midline_angle_deg"] == pytest.approx(90.0)
    assert hq.SHIPPED_MODEL.predict(m) == "good"


def test_strong_shear_is_bad():
    S = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    m = hq.pair_metrics(S, S, W, H)
    # midlines: x' = (W, 0), y' = (0.3 H, H): angle = atan2(H, 0.3 H) = 73.30 deg.
    assert m["l_midline_angle_deg"] == pytest.approx(math.degrees(math.atan2(1.0, 0.3)), abs=1e-9)
    assert m["l_shear"] == pytest.approx(0.3, rel=1e-9)
    assert m["max_corner_disp"] > 0.1
    assert hq.SHIPPED_MODEL.predict(m) == "bad"


def test_corner_sent_to_infinity_is_bad_and_has_no_nan():
    # w' = 1 - x/(2W) - y/(2H): 0.5 at the centre, exactly 0 at the corner (W, H), which goes to infinity.
    P = np.array([[1.0, 0, 0], [0, 1.0, 0], [-0.5 / W, -0.5 / H, 1.0]])
    m = hq.pair_metrics(P, np.eye(3), W, H)
    assert m["l_bounded"] is False and m["bounded"] is False and m["r_bounded"] is True
    assert m["l_min_w_ratio"] == pytest.approx(0.0, abs=1e-12)  # w'(corner) / w'(centre)
    assert m["l_projective_span"] == pytest.approx(1.0)
    assert m["max_corner_disp"] is None and "unbounded" in m["reasons"]["l_corner_disp_max"]
    assert hq.SHIPPED_MODEL.predict(m) == "bad"
    result = hq.assess(hq.HomographyPair("00001", P, np.eye(3)), size=(W, H))
    assert result["verdict"] == "bad" and result["metrics"]["score"] is None
    json.dumps(result, allow_nan=False)


def test_beyond_infinity_flip_is_bad():
    P = np.array([[1.0, 0, 0], [0, 1.0, 0], [-2.0 / W, 0, 1.5]])  # w' < 0 on the right part
    m = hq.pair_metrics(np.eye(3), P, W, H)
    assert m["r_bounded"] is False
    assert hq.assess(hq.HomographyPair("x", np.eye(3), P), size=(W, H))["verdict"] == "bad"


def test_left_right_row_consistency():
    down = np.array([[1.0, 0, 0], [0, 1.0, 8.0], [0, 0, 1.0]])
    m = hq.pair_metrics(np.eye(3), down, W, H)
    assert m["lr_row_offset"] == pytest.approx(-8.0 / H)
    assert m["lr_row_spread"] == pytest.approx(0.0, abs=1e-12)
    tall = np.diag([1.0, 1.02, 1.0])
    m2 = hq.pair_metrics(np.eye(3), tall, W, H)
    assert m2["lr_vscale_ratio"] == pytest.approx(1 / 1.02)
    assert m2["lr_row_spread"] == pytest.approx(0.01, abs=1e-9)  # 0.02 * H/2 / H at top and bottom rows


def test_indicator_values_match_keystonedepth_definition():
    H_row = np.array([[1.0, 0.0305, 2.4e-5], [-0.0305, 1.0, -1.19e-6], [-216, -315, 0.994]])
    m = hq.single_metrics(hq.row_to_column(H_row), W, H)
    assert m["projective_log10"] == pytest.approx(-math.log10(math.hypot(2.4e-5, 1.19e-6) / 0.994))
    assert abs(m["rotation_deg"]) == pytest.approx(math.degrees(math.atan2(0.0305, 1.0)))


def test_fit_and_cross_validate_recover_a_clean_rule():
    rng = np.random.default_rng(3)
    rows, labels = [], []
    for lab, lo, hi in (("good", 0.0, 0.05), ("border", 0.06, 0.08), ("bad", 0.1, 0.3)):
        for v in rng.uniform(lo, hi, 12):
            rows.append({"bounded": True, "max_corner_disp": float(v)})
            labels.append(lab)
    model = hq.fit_verdict(rows, labels)
    assert 0.05 <= model.t_border <= 0.06 and 0.08 <= model.t_bad <= 0.1
    cv = hq.cross_validate(rows, labels, k=4, repeats=3)
    assert cv["mean"] == 1.0 and cv["n"] == 36


def test_parse_id():
    assert hq.parse_id("/x/04733_rectification_mats.mat") == "04733"
    assert hq.parse_id("pair.json") == "pair"


def test_project_json_reader(tmp_path: Path):
    f = tmp_path / "04733.json"
    f.write_text(
        json.dumps(
            {
                "H_l": np.eye(3).tolist(),
                "H_r": np.eye(3).tolist(),
                "width": 640,
                "height": 480,
                "convention": "column",
            }
        )
    )
    (pair,) = hq.read_homographies(f)
    assert pair.id == "04733" and (pair.width, pair.height) == (640.0, 480.0)
    r = hq.assess(pair)
    assert r["metrics"]["width"] == 640.0 and r["metrics"]["size_source"] == "file" and r["verdict"] == "good"


def test_bad_files_raise_typed_errors(tmp_path: Path):
    bad = tmp_path / "12345_rectification_mats.mat"
    bad.write_bytes(b"not matlab")
    with pytest.raises(hq.HomographyReadError):
        hq.read_homographies(bad)
    j = tmp_path / "x.json"
    j.write_text(json.dumps({"H_l": [[1, 0], [0, 1]], "H_r": np.eye(3).tolist()}))
    with pytest.raises(hq.HomographyReadError, match="3x3"):
        hq.read_homographies(j)


# ---------------------------------------------------------------- real KeystoneDepth files


@pytest.fixture
def kd(shared_data: Path) -> Path:
    root = shared_data / "keystonedepth"
    if not (root / "labels.csv").exists():
        pytest.skip("keystonedepth data not present")
    return root


def test_mat_and_json_agree_and_match_their_indicator(kd: Path):
    (pair,) = hq.read_homographies(kd / "homographies" / "04733_rectification_mats.mat")
    by_id = {p.id: p for p in hq.read_homographies(kd / "homographies.json")}
    assert pair.id == "04733" and len(by_id) == 329
    np.testing.assert_allclose(pair.H_l, by_id["04733"].H_l)
    np.testing.assert_allclose(pair.H_r, by_id["04733"].H_r)
    # Their indicator for 04733 (indicators/test/*_r1_60.json): projective 4.6, rotation 1.7 deg.
    m = hq.single_metrics(pair.H_l, *hq.DEFAULT_SIZE)
    assert round(m["projective_log10"], 1) == 4.6 and round(abs(m["rotation_deg"]), 1) == 1.7
    assert hq.assess(pair)["verdict"] == "good"  # human label: good


def test_inferred_crop_size_makes_keystonedepth_midlines_perpendicular(kd: Path):
    # Their rectified view of 04733 is drawn on the warped crop's bounding box: solving for the crop
    # size gives one at which Loop-Zhang's shearing step keeps the midlines at 90 deg.
    from PIL import Image

    (pair,) = hq.read_homographies(kd / "homographies" / "04733_rectification_mats.mat")
    with Image.open(kd / "rectified_left_vis" / "train" / "good" / "04733.png") as im:
        size = hq.infer_input_size(pair.H_l, *im.size)
    assert size is not None and 450 < size[0] < 800 and 450 < size[1] < 900
    assert hq.single_metrics(pair.H_l, *size)["midline_dev_deg"] < 0.05


def test_shipped_model_cross_validated_beats_their_indicator(kd: Path):
    labels = hq.read_labels(kd / "labels.csv")
    pairs = {p.id: p for p in hq.read_homographies(kd / "homographies.json")}
    ids = sorted(labels)
    assert len(ids) == 100 and all(i in pairs for i in ids)
    rows = [hq.pair_metrics(pairs[i].H_l, pairs[i].H_r, *hq.DEFAULT_SIZE) for i in ids]
    y = [labels[i] for i in ids]
    cv = hq.cross_validate(rows, y, k=5, repeats=50, seed=0)
    assert cv["mean"] >= 0.78
    assert cv["mean"] == pytest.approx(0.8746, abs=1e-9) and cv["sd"] == pytest.approx(0.0223, abs=1e-4)
    refit = hq.fit_verdict(rows, y)
    assert refit.t_border == pytest.approx(hq.SHIPPED_MODEL.t_border)
    assert refit.t_bad == pytest.approx(hq.SHIPPED_MODEL.t_bad)
    shipped = sum(hq.SHIPPED_MODEL.predict(r) == lab for r, lab in zip(rows, y, strict=True))
    assert shipped == 92


def test_shipped_model_on_held_out_batch(kd: Path):
    pairs = {p.id: p for p in hq.read_homographies(kd / "homographies.json")}
    labels = hq.read_labels(kd / "labels.csv")
    held = {}
    for lab in ("good", "bad", "border"):
        f = kd / "indicators" / "test" / f"proj_components_r1_{lab}.json"
        if not f.exists():
            pytest.skip("held-out batch not present")
        held.update({item[0]: lab for item in json.loads(f.read_text()).values()})
    assert len(held) == 108 and not set(held) & set(labels)
    correct = sum(hq.assess(pairs[i])["verdict"] == lab for i, lab in held.items())
    assert correct == 100  # 0.926


def test_mat_reader_transposes_row_vector_matrices(tmp_path: Path):
    from scipy.io import savemat

    tl = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-215.0, 40.0, 1.0]])
    tr = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-200.0, 40.0, 1.0]])
    f = tmp_path / "04733_rectification_mats.mat"
    savemat(f, {"tl": tl, "tr": tr})
    (pair,) = hq.read_homographies(f)
    assert pair.id == "04733" and pair.convention_read == "row"
    xy, _ = hq.apply_homography(pair.H_l, [[10.0, 20.0]])
    assert xy[0].tolist() == [-205.0, 60.0]
    np.testing.assert_array_equal(pair.H_r, tr.T)
    savemat(tmp_path / "00001_rectification_mats.mat", {"tl": tl})
    with pytest.raises(hq.HomographyReadError, match="missing variable"):
        hq.read_homographies(tmp_path / "00001_rectification_mats.mat")
