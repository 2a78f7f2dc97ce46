"""Contracts checked at the door of every stage: image arrays and their sizes."""

from __future__ import annotations

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
        raise InvalidInputError(
            f"Expected {name} of at least {min_width}x{min_height} px (W x H), got {width}x{height}"
        )
    return image
