"""What every format writer shares: a card's payload, the file ledger, byte-reproducible encoders.

:func:`build_payload` reads a card's files once; each format's writer (one module per format in
:mod:`exports.formats`) takes the :class:`CardPayload` one card at a time and keeps at most one
shard's buffer in memory. Everything is byte-reproducible: PNGs are encoded with fixed settings
and no metadata (or copied byte for byte), EXR with fixed compression, and no file holds an
absolute path. Every file written is recorded in the :class:`FileLedger` with its sha256.
No database here.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .records import VIEW_NAMES, ReleaseCard

PNG_COMPRESS_LEVEL = 3  # as pipeline.io.write_png: level 6 took twice the time for ~5 % smaller files


class FileLedger:
    """Paths (relative to the release root, POSIX) -> (sha256 hex, bytes) of every file written."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.files: dict[str, tuple[str, int]] = {}

    def write_bytes(self, relative: str, data: bytes) -> None:
        target = self.root / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
        self.files[relative] = (hashlib.sha256(data).hexdigest(), len(data))

    def record_file(self, relative: str) -> None:
        digest = hashlib.sha256()
        size = 0
        with open(self.root / relative, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
                size += len(block)
        self.files[relative] = (digest.hexdigest(), size)

    @property
    def total_bytes(self) -> int:
        return sum(size for _, size in self.files.values())


def encode_png(image: np.ndarray) -> bytes:
    """PNG with fixed settings and no metadata chunks: the same pixels give the same bytes."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buffer.getvalue()


def encode_npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array, np.float32), allow_pickle=False)
    return buffer.getvalue()


def encode_exr(array: np.ndarray, scratch: Path) -> bytes:
    """One float32 channel ``Y`` in a ZIP-compressed scanline EXR (OpenCV 5 cannot write EXR).

    Non-finite values are kept: NaN marks pixels without a disparity."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.ascontiguousarray(array, np.float32)}) as handle:
        handle.write(str(scratch))
    try:
        return scratch.read_bytes()
    finally:
        scratch.unlink(missing_ok=True)


def read_exr(path: str | os.PathLike[str]) -> np.ndarray:
    """The ``Y`` channel of an EXR written by :func:`encode_exr`, ``(H, W)`` float32."""
    import OpenEXR

    with OpenEXR.File(str(path)) as handle:
        return np.asarray(handle.channels()["Y"].pixels, np.float32)


def _load_map(path: Path, name: str) -> np.ndarray:
    array = np.load(path, allow_pickle=False)
    if array.ndim != 2 or array.size == 0:
        raise ValueError(f"{name} must be a non-empty 2-D map, got shape {array.shape}")
    return np.asarray(array, np.float32)


@dataclass
class ViewsPayload:
    """A card's five GD images as released: PNG bytes (v0..v4), depth maps ((H, W) float32,
    finite and > 0), the cameras document (``depth`` entries already naming the EXR files) and
    the preview WebP bytes."""

    images: list[bytes]
    depths: list[np.ndarray]
    scene: dict[str, Any]
    preview: bytes


def read_views(card: ReleaseCard) -> ViewsPayload:
    """Read and check a card's views artifacts (raises ``ValueError``/``OSError`` on bad input)."""
    scene = json.loads(card.views["scene"].read_text())
    if not isinstance(scene, dict) or len(scene.get("views") or []) != len(VIEW_NAMES):
        raise ValueError(f"views.json does not describe {len(VIEW_NAMES)} views")
    for view in scene["views"]:
        view["depth"] = f"{view['name']}_depth.exr"
        for web_only in ("web_image", "mesh"):  # the viewer's JPEG and mesh PNG stay out of releases
            view.pop(web_only, None)
    scene.pop("mesh", None)
    depths = [_load_map(card.views[f"{name}_depth"], f"{name}_depth") for name in VIEW_NAMES]
    if any(depth.shape != depths[0].shape for depth in depths):
        raise ValueError("the five views' depth maps differ in size")
    if not all(np.isfinite(depth).all() and (depth > 0).all() for depth in depths):
        raise ValueError("a view's depth map is not finite and > 0 everywhere")
    return ViewsPayload(
        images=[card.views[name].read_bytes() for name in VIEW_NAMES],
        depths=depths,
        scene=scene,
        preview=card.views["preview"].read_bytes(),
    )


@dataclass
class CardPayload:
    """A card's released bytes and arrays, built once and shared by every writer."""

    card: ReleaseCard
    original: bytes
    original_suffix: str
    cropped_left: bytes
    cropped_right: bytes
    rectified_left: bytes
    rectified_right: bytes
    disparity_left: np.ndarray  # (H, W) float32 px, rectified-view pixels
    disparity_right: np.ndarray
    depth_512: np.ndarray  # (512, 512) float32, depth up to scale
    record: dict[str, Any]
    views: ViewsPayload | None = None

    @property
    def record_json(self) -> bytes:
        return json.dumps(self.record, sort_keys=True, ensure_ascii=False, allow_nan=False).encode()

    @property
    def size(self) -> int:
        return (
            len(self.original)
            + len(self.cropped_left)
            + len(self.cropped_right)
            + len(self.rectified_left)
            + len(self.rectified_right)
            + self.disparity_left.nbytes
            + self.disparity_right.nbytes
            + self.depth_512.nbytes
        )


def build_payload(card: ReleaseCard) -> CardPayload:
    """Read a card's files and cut its cropped views (raises ``ValueError``/``OSError`` on bad input).

    Views are optional: unreadable views leave the card released without them, the payload's
    card saying why (``views_note``), so its manifest entry and record match what is written."""
    from pipeline.io import read_image

    views: ViewsPayload | None = None
    if card.views:
        try:
            views = read_views(card)
        except (OSError, ValueError) as exc:
            card = replace(card, views={}, views_note=f"views unreadable: {exc}")

    scan = read_image(card.original)
    if "rotated 180 deg" in card.orientation:
        scan = np.ascontiguousarray(scan[::-1, ::-1])
    if "intensities inverted" in card.orientation:
        scan = 255 - scan
    crops = []
    for box in (card.left_box, card.right_box):
        x0, y0, x1, y1 = box
        if not (0 <= x0 < x1 <= scan.shape[1] and 0 <= y0 < y1 <= scan.shape[0]):
            raise ValueError(f"crop box {box} lies outside the {scan.shape[1]} x {scan.shape[0]} card")
        crops.append(encode_png(scan[y0:y1, x0:x1]))
    return CardPayload(
        card=card,
        original=card.original.read_bytes(),
        original_suffix=card.original.suffix.lower() or ".bin",
        cropped_left=crops[0],
        cropped_right=crops[1],
        rectified_left=card.rectified_left.read_bytes(),
        rectified_right=card.rectified_right.read_bytes(),
        disparity_left=_load_map(card.disparity_left, "disparity_left"),
        disparity_right=_load_map(card.disparity_right, "disparity_right"),
        depth_512=_load_map(card.depth_512, "depth_512"),
        record=card.record(),
        views=views,
    )
