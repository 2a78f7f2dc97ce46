"""Fixtures for the pipeline tests: where the shared real test data lives."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from pipeline.io import read_image


def shared_data_path() -> Path:
    """``$KEYSTONE_SHARED_DATA`` if set, else ``../shared/data`` next to the repository."""
    override = os.environ.get("KEYSTONE_SHARED_DATA")
    return Path(override) if override else Path(__file__).resolve().parents[3] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of the shared real test data; skips the test when it is absent."""
    path = shared_data_path()
    if not path.is_dir():
        pytest.skip("../shared/data not present: real-data tests need the shared test data")
    return path


@pytest.fixture(scope="session")
def load_card(shared_data: Path) -> Callable[[str], np.ndarray]:
    """Read a card by its path under ``stereocards/``. ``cropped_pairs/depthy_7995`` ships as two
    views in two files: they are put side by side (cut to the shorter height) to make a card."""

    def load(name: str) -> np.ndarray:
        root = shared_data / "stereocards"
        if name == "cropped_pairs/depthy_7995":
            left = read_image(root / name / "7995l-image.jpg")
            right = read_image(root / name / "7995r-image.jpg")
            height = min(left.shape[0], right.shape[0])
            return np.hstack([left[:height], right[:height]])
        return read_image(root / name)

    return load
