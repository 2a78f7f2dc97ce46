"""The training script of the learned upright head: its L2 rule, its augmentations, its table."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import skimage.data

from benchmarks.upright import augment, chosen_l2, feature_table
from pipeline.upright import FEATURE_SIZE


def test_the_largest_l2_within_a_quarter_of_the_best_loss_is_chosen():
    sweep = {0.1: {"log_loss": 0.10}, 1.0: {"log_loss": 0.12}, 3.0: {"log_loss": 0.125}, 10.0: {"log_loss": 0.2}}
    assert chosen_l2(sweep) == 3.0
    assert chosen_l2({1.0: {"log_loss": 0.3}}) == 1.0


def test_augmented_copies_are_crops_of_70_to_100_percent():
    photo = skimage.data.astronaut()
    rng = np.random.default_rng(0)
    for _ in range(20):
        copy = augment(photo, rng)
        assert copy.dtype == np.uint8 and copy.ndim == 3
        assert 0.7 * 512 - 1 <= copy.shape[0] <= 512 and 0.7 * 512 - 1 <= copy.shape[1] <= 512


@pytest.mark.skipif(
    importlib.util.find_spec("efficientnet_lite_pytorch") is None, reason="efficientnet-lite-pytorch not installed"
)
def test_the_table_gives_each_photo_a_row_each_way_up():
    photos = [("astronaut", skimage.data.astronaut()), ("coffee", skimage.data.coffee())]
    table = feature_table(photos, 96, copies=1, seed=0)
    # (1 photo + 1 copy) x 2 ways up, for both photos
    assert table["turn"].shape == table["tone"].shape == (8, FEATURE_SIZE)
    assert list(table["sources"]) == ["astronaut"] * 4 + ["coffee"] * 4
    assert list(table["augmented"]) == [False, True, False, True] * 2
    # the turn rows are given twice (the turned photo's row is the negation: the same loss)
    assert np.allclose(table["turn"][0], table["turn"][2])
