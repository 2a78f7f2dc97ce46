"""``keystone check-homographies``: JSON shape, verdicts, per-file errors and exit status.

Invokes the click command directly: no database, no app context."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from app.geometry import check_homographies_command


def _write(path: Path, H_l: np.ndarray, H_r: np.ndarray, **extra: object) -> Path:
    path.write_text(
        json.dumps(
            {"H_l": H_l.tolist(), "H_r": H_r.tolist(), "convention": "column", **extra}
        )
    )
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
    result = CliRunner().invoke(
        check_homographies_command, [str(good), str(broken), str(far), "--json"]
    )
    assert result.exit_code == 1
    doc = json.loads(result.output)  # strict JSON: no NaN / Infinity tokens
    assert "NaN" not in result.output and "Infinity" not in result.output
    by_id = {r["id"]: r for r in doc["results"]}
    assert by_id["04771"]["error"] and "verdict" not in by_id["04771"]
    assert by_id["04733"]["verdict"] == "good"
    assert (
        by_id["04773"]["verdict"] == "bad"
        and by_id["04773"]["metrics"]["bounded"] is False
    )


def test_table_output(tmp_path: Path):
    _write(tmp_path / "04733.json", np.eye(3), np.eye(3))
    result = CliRunner().invoke(
        check_homographies_command, [str(tmp_path / "04733.json")]
    )
    assert result.exit_code == 0
    assert (
        "04733" in result.output
        and "good" in result.output
        and "1 item(s): 1 good" in result.output
    )


def test_size_option(tmp_path: Path):
    _write(tmp_path / "04733.json", np.eye(3), np.eye(3))
    result = CliRunner().invoke(
        check_homographies_command, [str(tmp_path), "--size", "500x400", "--json"]
    )
    assert json.loads(result.output)["results"][0]["metrics"]["width"] == 500.0
    bad = CliRunner().invoke(
        check_homographies_command, [str(tmp_path), "--size", "big"]
    )
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
    assert by_id["04857"]["metrics"]["min_projective_log10"] == pytest.approx(
        2.74, abs=0.02
    )


def test_folder_scan_skips_non_homography_json(tmp_path: Path):
    _write(tmp_path / "04733.json", np.eye(3), np.eye(3))
    (tmp_path / "proj_components_r1_60.json").write_text(
        json.dumps({"0": ["04733", 4.6]})
    )
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
