"""Fixtures for the pipeline tests: real cards from ../shared/data (``shared_data`` is the root conftest's)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from pipeline.io import read_image


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
