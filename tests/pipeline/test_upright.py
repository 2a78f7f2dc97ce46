"""The learned upright / positive heads: contracts, the head file, antisymmetry, real photos."""

from __future__ import annotations

import json

import numpy as np
import pytest
import skimage.data

from pipeline.errors import InvalidInputError
from pipeline.upright import (
    FEATURE_SIZE,
    HEAD_FILE,
    SHIPPED_HEAD_VERSION,
    UprightHead,
    UprightInputError,
    UprightModelMissingError,
    fit_linear_head,
    load_head,
    margin_summary,
    read_learned_differences,
    shipped_head,
    tone_difference,
    turn_difference,
    turned,
    view_features,
    write_learned_differences,
)

needs_backbone = pytest.mark.skipif(
    __import__("importlib").util.find_spec("efficientnet_lite_pytorch") is None,
    reason="efficientnet-lite-pytorch is not installed (see the README's install line)",
)


def test_shipped_head_file_matches_the_version_the_step_hashes():
    data = json.loads(HEAD_FILE.read_text())
    assert data["version"] == SHIPPED_HEAD_VERSION
    head = shipped_head()
    assert len(head.turn) == len(head.tone) == FEATURE_SIZE
    # trained only on material the project may use that way: never KeystoneDepth or Keystone-Mast
    assert not any(source.isdigit() or source.startswith(("kd/", "km/")) for source in data["trained_on"])


def test_head_contract():
    with pytest.raises(InvalidInputError, match="1280 finite turn weights"):
        UprightHead("x", 224, (0.0,) * 3, (0.0,) * FEATURE_SIZE)
    with pytest.raises(InvalidInputError, match="finite"):
        UprightHead("x", 224, (float("nan"),) * FEATURE_SIZE, (0.0,) * FEATURE_SIZE)
    with pytest.raises(InvalidInputError, match="input side"):
        UprightHead("x", 20, (0.0,) * FEATURE_SIZE, (0.0,) * FEATURE_SIZE)
    with pytest.raises(InvalidInputError, match="version, input_side"):
        UprightHead.from_dict({"version": "x"})


def test_refit_head_loads_from_its_file_and_a_missing_one_is_a_typed_error(tmp_path):
    head = UprightHead("c-1", 160, tuple(np.linspace(-1, 1, FEATURE_SIZE)), (0.5,) * FEATURE_SIZE)
    path = tmp_path / "head.json"
    path.write_text(json.dumps(head.as_dict()))
    assert load_head(str(path)) == head
    with pytest.raises(UprightModelMissingError, match="cannot be read"):
        load_head(str(tmp_path / "absent.json"))
    path.write_text("{not json")
    with pytest.raises(UprightModelMissingError):
        load_head(str(path))


def test_fit_recovers_a_separating_direction_and_checks_its_input():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=FEATURE_SIZE)
    x = rng.normal(size=(1500, FEATURE_SIZE))
    x *= np.sign(x @ truth)[:, None]  # every row signed so its right answer is +1
    w = fit_linear_head(x, l2=1.0)
    cosine = float(w @ truth / np.linalg.norm(w) / np.linalg.norm(truth))
    assert cosine > 0.6  # measured 0.74 (1500 rows in 1280 dimensions)
    held = rng.normal(size=(200, FEATURE_SIZE))
    held *= np.sign(held @ truth)[:, None]
    assert margin_summary(held @ w)["accuracy"] > 0.7  # 1 - arccos(0.74) / pi = 0.76
    # a strong pull towards a prior keeps the fit there
    prior = rng.normal(size=FEATURE_SIZE)
    near = fit_linear_head(x, l2=1e6, prior=prior)
    assert np.abs(near - prior).max() < 0.01
    with pytest.raises(InvalidInputError, match="finite differences"):
        fit_linear_head(np.full((3, FEATURE_SIZE), np.nan), l2=1.0)
    with pytest.raises(InvalidInputError, match="L2"):
        fit_linear_head(x, l2=0.0)


def test_margin_summary_counts():
    summary = margin_summary(np.array([3.0, 1.0, -0.5, -2.5]))
    assert summary == {"n": 4, "right": 2, "accuracy": 0.5, "decided": 2, "decided_wrong": 1, "log_loss": summary["log_loss"]}
    assert summary["log_loss"] > 0


def test_differences_round_trip_as_float16(tmp_path):
    diff = {"turn": np.linspace(-3, 3, 2 * FEATURE_SIZE, dtype=np.float32).reshape(2, FEATURE_SIZE)}
    back = read_learned_differences(write_learned_differences(tmp_path / "d.npz", diff))
    assert set(back) == {"turn"} and back["turn"].dtype == np.float32
    assert np.abs(back["turn"] - diff["turn"]).max() < 3e-3


@pytest.mark.parametrize(
    "photo, message",
    [
        (np.zeros((20, 100, 3), np.uint8), "at least 32"),
        (np.zeros((64, 64, 3), np.float32), "uint8"),
        (np.zeros((64, 64, 4), np.uint8), "shape"),
        ("not an array", "numpy array"),
    ],
)
def test_bad_photos_are_typed_errors(photo, message):
    with pytest.raises(UprightInputError, match=message):
        view_features([photo], 224)


@needs_backbone
def test_the_shipped_head_reads_real_photos_both_ways_up():
    """scikit-image's photos ship with the install (some were in the head's training set, so this
    checks the wiring, not generalisation: ``python -m benchmarks.upright`` measures that)."""
    head = shipped_head()
    photos = [skimage.data.astronaut(), skimage.data.coffee(), skimage.data.stereo_motorcycle()[0]]
    features = view_features(photos, head.input_side)
    upright = head.margins("turn", turn_difference(features))
    assert (upright > 1.0).all(), upright
    # antisymmetric by construction: the turned photo gets exactly the opposite answer
    back = view_features([turned(p) for p in photos], head.input_side, ("as_given", "turned"))
    assert np.allclose(head.margins("turn", turn_difference(back)), -upright, atol=1e-3)
    positive = head.margins("tone", tone_difference(features))
    assert (positive > 0.5).all(), positive
    negatives = view_features([255 - p for p in photos], head.input_side)
    assert (head.margins("tone", tone_difference(negatives)) < -0.5).all()


@needs_backbone
def test_grey_and_tiny_but_valid_photos_work():
    head = shipped_head()
    grey = skimage.data.camera()
    features = view_features([grey, grey[:40, :40]], head.input_side, ("as_given", "turned"))
    assert features["as_given"].shape == (2, FEATURE_SIZE)
    assert np.isfinite(features["turned"]).all()
    # a blank photo has no way up: the same features both ways, margin 0
    blank = view_features([np.full((64, 64), 128, np.uint8)], head.input_side, ("as_given", "turned"))
    assert abs(float(head.margins("turn", turn_difference(blank))[0])) < 1e-6
