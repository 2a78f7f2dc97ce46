"""Format writers: KeystoneDepth folders, Parquet shards, WebDataset tars, views. No database here.

Each writer takes one :class:`CardPayload` at a time and keeps at most one shard's buffer
(Parquet: one row group) in memory. Everything is byte-reproducible: PNGs are encoded with
fixed settings and no metadata (or copied byte for byte), tar members carry the release date
as their time and no owner, Parquet files carry no write time, and no file holds an absolute
path. Every file written is recorded in the :class:`FileLedger` with its sha256.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tarfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .records import VIEW_NAMES, VIEWS_FOLDER, ReleaseCard

PNG_COMPRESS_LEVEL = 3  # as pipeline.io.write_png: level 6 took twice the time for ~5 % smaller files
PARQUET_ROW_GROUP = 16  # cards per row group at most
# ... and payload bytes per row group at most: Arrow copies a row group two to three times on its
# way into the file, so 16 real-size cards (~10 MB each: 800 x 600 views and maps) peaked at 620 MB.
PARQUET_ROW_GROUP_BYTES = 24 * 1024 * 1024
SHARD_BYTES = 256 * 1024 * 1024  # start a new shard past this many payload bytes
TAR_SHARD_CARDS = 1000

# KeystoneDepth's published layout (as third-party loaders read it), plus our extra files.
KD_CROPPED = "cropped/cropped_full_LR"
KD_DISPARITY = "processed/rectified/disp_info_LR"
KD_RECTIFIED = "processed/rectified/rectified_LR"
KD_RECTIFICATION = "processed/rectified/rectification"
KD_DEPTH = "processed/depth_512"
KD_ORIGINAL = "original"


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


class KeystoneDepthWriter:
    """``cropped/cropped_full_LR/<id>L.png``, ``processed/rectified/disp_info_LR/<id>L.exr`` and
    the rest of the folders, one file per view and map."""

    name = "keystonedepth"

    def __init__(self, ledger: FileLedger, scratch: Path) -> None:
        self.ledger, self.scratch = ledger, scratch

    def add(self, payload: CardPayload) -> None:
        key, ledger = payload.card.key, self.ledger
        ledger.write_bytes(f"{KD_ORIGINAL}/{key}{payload.original_suffix}", payload.original)
        ledger.write_bytes(f"{KD_CROPPED}/{key}L.png", payload.cropped_left)
        ledger.write_bytes(f"{KD_CROPPED}/{key}R.png", payload.cropped_right)
        ledger.write_bytes(f"{KD_RECTIFIED}/{key}L.png", payload.rectified_left)
        ledger.write_bytes(f"{KD_RECTIFIED}/{key}R.png", payload.rectified_right)
        ledger.write_bytes(f"{KD_DISPARITY}/{key}L.exr", encode_exr(payload.disparity_left, self.scratch))
        ledger.write_bytes(f"{KD_DISPARITY}/{key}R.exr", encode_exr(payload.disparity_right, self.scratch))
        ledger.write_bytes(f"{KD_DEPTH}/{key}.exr", encode_exr(payload.depth_512, self.scratch))
        rectification = payload.record["rectification"]
        ledger.write_bytes(
            f"{KD_RECTIFICATION}/{key}.json", json.dumps(rectification, sort_keys=True, indent=1, allow_nan=False).encode()
        )

    def close(self) -> None:
        pass


# ---- Parquet, loadable by Hugging Face `datasets` -------------------------------------------

IMAGE_COLUMNS = ("original", "cropped_left", "cropped_right", "rectified_left", "rectified_right")
MAP_COLUMNS = ("disparity_left", "disparity_right", "depth_512")
STRING_COLUMNS = (
    "key",
    "accession",
    "collection",
    "title",
    "date",
    "museum_url",
    "grade",
    "review_decision",
    "automatic_grade",
    "metadata_json",
    "pipeline_json",
    "digest",
)
MATRIX_COLUMNS = ("H_l", "H_r", "K", "R")


def parquet_schema():  # type: ignore[no-untyped-def]
    """The Arrow schema of every shard, with the ``huggingface`` features entry that makes
    ``datasets`` decode the image columns as images (struct of bytes and path)."""
    import pyarrow as pa

    image = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    fields = [pa.field("card_id", pa.int64())]
    fields += [pa.field(name, pa.string()) for name in STRING_COLUMNS]
    fields += [pa.field("left_box", pa.list_(pa.int32())), pa.field("right_box", pa.list_(pa.int32()))]
    fields += [pa.field(name, pa.list_(pa.list_(pa.float64()))) for name in MATRIX_COLUMNS]
    fields += [pa.field("t", pa.list_(pa.float64()))]
    fields += [pa.field(name, image) for name in IMAGE_COLUMNS]
    fields += [pa.field(name, pa.list_(pa.list_(pa.float32()))) for name in MAP_COLUMNS]

    def value(dtype: str) -> dict[str, Any]:
        return {"dtype": dtype, "_type": "Value"}

    def listed(feature: dict[str, Any]) -> dict[str, Any]:
        return {"feature": feature, "_type": "List"}

    features: dict[str, Any] = {"card_id": value("int64")}
    features.update({name: value("string") for name in STRING_COLUMNS})
    features.update({name: listed(value("int32")) for name in ("left_box", "right_box")})
    features.update({name: listed(listed(value("float64"))) for name in MATRIX_COLUMNS})
    features["t"] = listed(value("float64"))
    features.update({name: {"_type": "Image"} for name in IMAGE_COLUMNS})
    features.update({name: listed(listed(value("float32"))) for name in MAP_COLUMNS})
    ordered = {field.name: features[field.name] for field in fields}
    metadata = {b"huggingface": json.dumps({"info": {"features": ordered}}, sort_keys=False).encode()}
    return pa.schema(fields, metadata=metadata)


def _map_column(maps: list[np.ndarray]):  # type: ignore[no-untyped-def]
    """``list<list<float32>>`` from 2-D arrays without going through Python lists."""
    import pyarrow as pa

    row_offsets = np.zeros(len(maps) + 1, np.int32)
    row_offsets[1:] = np.cumsum([m.shape[0] for m in maps])
    widths = np.concatenate([np.full(m.shape[0], m.shape[1], np.int64) for m in maps]) if maps else np.zeros(0, np.int64)
    value_offsets = np.zeros(len(widths) + 1, np.int64)
    value_offsets[1:] = np.cumsum(widths)
    values = np.concatenate([m.ravel() for m in maps]) if maps else np.zeros(0, np.float32)
    rows = pa.ListArray.from_arrays(pa.array(value_offsets.astype(np.int32)), pa.array(values, pa.float32()))
    return pa.ListArray.from_arrays(pa.array(row_offsets), rows)


class ParquetWriter:
    """``data/train-<n>-of-<N>.parquet`` shards (Hugging Face's naming), ZSTD, row groups of
    :data:`PARQUET_ROW_GROUP` cards or :data:`PARQUET_ROW_GROUP_BYTES` payload bytes, whichever
    comes first."""

    name = "parquet"

    def __init__(self, ledger: FileLedger) -> None:
        self.ledger = ledger
        self.schema = parquet_schema()
        self.rows: list[CardPayload] = []
        self.group_bytes = 0
        self.writer: Any = None
        self.shard_bytes = 0
        self.shards: list[str] = []
        self.row_counts: list[int] = []

    def add(self, payload: CardPayload) -> None:
        if self.writer is not None and self.shard_bytes + payload.size > SHARD_BYTES:
            self._flush()
            self._close_shard()
        self.rows.append(payload)
        self.shard_bytes += payload.size
        self.group_bytes += payload.size
        if len(self.rows) >= PARQUET_ROW_GROUP or self.group_bytes >= PARQUET_ROW_GROUP_BYTES:
            self._flush()

    def _flush(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        if not self.rows:
            return
        if self.writer is None:
            relative = f"data/.shard-{len(self.shards):05d}.parquet"
            (self.ledger.root / "data").mkdir(parents=True, exist_ok=True)
            self.writer = pq.ParquetWriter(
                self.ledger.root / relative, self.schema, compression="zstd", compression_level=3, store_schema=True
            )
            self.shards.append(relative)
            self.row_counts.append(0)
        columns: dict[str, Any] = {}
        records = [p.record for p in self.rows]
        columns["card_id"] = pa.array([r["card_id"] for r in records], pa.int64())
        meta = [r["metadata"] for r in records]
        strings = {
            "key": [r["key"] for r in records],
            "accession": [r["accession"] for r in records],
            "collection": [r["collection"] for r in records],
            "title": [_text(m.get("title")) for m in meta],
            "date": [_text(m.get("date")) for m in meta],
            "museum_url": [r["museum_url"] for r in records],
            "grade": [r["grade"] for r in records],
            "review_decision": [r["review_decision"] for r in records],
            "automatic_grade": [r["automatic_grade"] for r in records],
            "metadata_json": [json.dumps(m, sort_keys=True, ensure_ascii=False) for m in meta],
            "pipeline_json": [json.dumps({"pipeline": r["pipeline"], "crowd": r["crowd"]}, sort_keys=True) for r in records],
            "digest": [r["digest"] for r in records],
        }
        for name in STRING_COLUMNS:
            columns[name] = pa.array(strings[name], pa.string())
        for name in ("left_box", "right_box"):
            columns[name] = pa.array([r[name] for r in records], pa.list_(pa.int32()))
        for name in MATRIX_COLUMNS:
            columns[name] = pa.array([r["rectification"].get(name) for r in records], pa.list_(pa.list_(pa.float64())))
        columns["t"] = pa.array([_flat(r["rectification"].get("t")) for r in records], pa.list_(pa.float64()))
        suffix = {
            "original": None,
            "cropped_left": "L.png",
            "cropped_right": "R.png",
            "rectified_left": "L.png",
            "rectified_right": "R.png",
        }
        for name in IMAGE_COLUMNS:
            columns[name] = pa.array(
                [{"bytes": getattr(p, name), "path": f"{p.card.key}{suffix[name] or p.original_suffix}"} for p in self.rows],
                self.schema.field(name).type,
            )
        for name in MAP_COLUMNS:
            columns[name] = _map_column([getattr(p, name) for p in self.rows])
        table = pa.Table.from_arrays([columns[f.name] for f in self.schema], schema=self.schema)
        self.writer.write_table(table, row_group_size=len(self.rows))
        self.row_counts[-1] += len(self.rows)
        self.rows = []
        self.group_bytes = 0

    def _close_shard(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
            self.shard_bytes = 0

    def close(self) -> None:
        self._flush()
        self._close_shard()
        total = len(self.shards)
        for number, relative in enumerate(self.shards):
            final = f"data/train-{number:05d}-of-{total:05d}.parquet"
            os.replace(self.ledger.root / relative, self.ledger.root / final)
            self.ledger.record_file(final)


def _text(value: Any) -> str | None:
    return None if value is None else str(value)


def _flat(value: Any) -> list[float] | None:
    return None if value is None else [float(v) for v in np.asarray(value, float).ravel()]


class WebDatasetWriter:
    """``webdataset/keystone-<n>.tar`` shards; members ``<key>.<field>.<ext>`` with dot-free keys."""

    name = "webdataset"

    def __init__(self, ledger: FileLedger, mtime: float) -> None:
        self.ledger, self.mtime = ledger, int(mtime)
        self.tar: tarfile.TarFile | None = None
        self.in_shard = 0
        self.count = 0
        self.current: str | None = None

    def _member(self, name: str, data: bytes) -> None:
        info = tarfile.TarInfo(name)
        info.size, info.mtime, info.mode = len(data), self.mtime, 0o644
        info.uid = info.gid = 0
        info.uname = info.gname = ""
        assert self.tar is not None
        self.tar.addfile(info, io.BytesIO(data))

    def add(self, payload: CardPayload) -> None:
        if self.tar is None or self.in_shard >= TAR_SHARD_CARDS:
            self._close_shard()
            self.current = f"webdataset/keystone-{self.count:06d}.tar"
            (self.ledger.root / "webdataset").mkdir(parents=True, exist_ok=True)
            self.tar = tarfile.open(self.ledger.root / self.current, "w", format=tarfile.USTAR_FORMAT)
            self.count += 1
        key = payload.card.key
        self._member(f"{key}.json", payload.record_json)
        self._member(f"{key}.cropped_left.png", payload.cropped_left)
        self._member(f"{key}.cropped_right.png", payload.cropped_right)
        self._member(f"{key}.left.png", payload.rectified_left)
        self._member(f"{key}.right.png", payload.rectified_right)
        self._member(f"{key}.disparity_left.npy", encode_npy(payload.disparity_left))
        self._member(f"{key}.disparity_right.npy", encode_npy(payload.disparity_right))
        self._member(f"{key}.depth_512.npy", encode_npy(payload.depth_512))
        self.in_shard += 1

    def _close_shard(self) -> None:
        if self.tar is not None and self.current is not None:
            self.tar.close()
            self.ledger.record_file(self.current)
            self.tar = None
            self.in_shard = 0

    def close(self) -> None:
        self._close_shard()


# ---- Views: the five GD images per card (optional component) ---------------------------------

VIEWS_INDEX = f"{VIEWS_FOLDER}/views.jsonl"


def view_files(key: str) -> tuple[str, ...]:
    """The release paths of one card's views, in the order they are written."""
    folder = f"{VIEWS_FOLDER}/{key}"
    return (
        *(f"{folder}/{name}.png" for name in VIEW_NAMES),
        *(f"{folder}/{name}_depth.exr" for name in VIEW_NAMES),
        f"{folder}/views.json",
        f"{folder}/preview.webp",
    )


class ViewsWriter:
    """``views/<key>/v0.png`` .. ``v4.png`` (8-bit grey, or RGB where the rectified view is colour;
    copied byte for byte), ``v<i>_depth.exr``
    (float32 channel ``Y``, depth along view i's -z axis, baseline 1, finite and > 0), ``views.json``
    (the cameras; its ``depth`` entries name the EXR files) and ``preview.webp`` (animated
    parallax), plus ``views/views.jsonl``, one line per card that has views. Cards without a
    finished views result are counted by reason in :attr:`without`."""

    name = "views"

    def __init__(self, ledger: FileLedger, scratch: Path) -> None:
        self.ledger, self.scratch = ledger, scratch
        (ledger.root / VIEWS_FOLDER).mkdir(parents=True, exist_ok=True)
        (ledger.root / VIEWS_INDEX).write_bytes(b"")
        self.closed = False
        self.with_views = 0
        self.without: dict[str, int] = {}

    def add(self, payload: CardPayload) -> None:
        card, views = payload.card, payload.views
        if views is None:
            reason = card.views_note or "views not run"
            self.without[reason] = self.without.get(reason, 0) + 1
            return
        key, ledger = card.key, self.ledger
        paths = view_files(key)
        for relative, data in zip(paths[:5], views.images):
            ledger.write_bytes(relative, data)
        for relative, depth in zip(paths[5:10], views.depths):
            ledger.write_bytes(relative, encode_exr(depth, self.scratch))
        ledger.write_bytes(paths[10], json.dumps(views.scene, sort_keys=True, indent=1, allow_nan=False).encode())
        ledger.write_bytes(paths[11], views.preview)
        scene = views.scene
        line = {
            "key": key,
            "card_id": card.card_id,
            "folder": f"{VIEWS_FOLDER}/{key}",
            "width": scene.get("width"),
            "height": scene.get("height"),
            "focal_px": scene["views"][0].get("focal_px"),
            "quad_radius": scene.get("quad_radius"),
            "preview": paths[11],
        }
        # Appended per card (not held open) so a release that stops half-way leaks no handle.
        with open(self.ledger.root / VIEWS_INDEX, "ab") as index:
            index.write(json.dumps(line, sort_keys=True, allow_nan=False).encode() + b"\n")
        self.with_views += 1

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.ledger.record_file(VIEWS_INDEX)
