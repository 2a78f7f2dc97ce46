"""``parquet``: one row per card in ``data/train-*.parquet`` shards that Hugging Face ``datasets``
loads as they are (image columns decode as images, maps are ``list<list<float32>>``).

Byte-reproducible: ZSTD at a fixed level, no write time in the files.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..writers import CardPayload, FileLedger
from .base import Problems, ReleaseFormat, WriteContext
from .registry import release_format


@dataclass(frozen=True)
class ParquetOptions:
    row_group_cards: int = 16  # cards per row group at most
    # ... and payload bytes per row group at most: Arrow copies a row group two to three times on its
    # way into the file, so 16 real-size cards (~10 MB each: 800 x 600 views and maps) peaked at 620 MB.
    row_group_bytes: int = 24 * 1024 * 1024
    shard_bytes: int = 256 * 1024 * 1024  # start a new shard past this many payload bytes


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
    :attr:`ParquetOptions.row_group_cards` cards or :attr:`ParquetOptions.row_group_bytes` payload
    bytes, whichever comes first."""

    def __init__(self, ledger: FileLedger, options: ParquetOptions | None = None) -> None:
        self.ledger = ledger
        self.options = options or ParquetOptions()
        self.schema = parquet_schema()
        self.rows: list[CardPayload] = []
        self.group_bytes = 0
        self.writer: Any = None
        self.shard_bytes = 0
        self.shards: list[str] = []
        self.row_counts: list[int] = []

    def add(self, payload: CardPayload) -> None:
        if self.writer is not None and self.shard_bytes + payload.size > self.options.shard_bytes:
            self._flush()
            self._close_shard()
        self.rows.append(payload)
        self.shard_bytes += payload.size
        self.group_bytes += payload.size
        if len(self.rows) >= self.options.row_group_cards or self.group_bytes >= self.options.row_group_bytes:
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

    def summary(self) -> dict[str, Any] | None:
        return None


def _text(value: Any) -> str | None:
    return None if value is None else str(value)


def _flat(value: Any) -> list[float] | None:
    return None if value is None else [float(v) for v in np.asarray(value, float).ravel()]


@release_format
class ParquetFormat(ReleaseFormat):
    name = "parquet"
    description = "Parquet shards for Hugging Face datasets: one row per card, images and maps as columns"
    order = 20
    default = True
    encodings = {".parquet": "application/x-parquet"}

    def default_options(self) -> ParquetOptions:
        return ParquetOptions()

    def writer(self, context: WriteContext) -> ParquetWriter:
        return ParquetWriter(context.ledger, self.options)

    def readme_header(self) -> list[str]:
        return ["configs:", "- config_name: default", "  data_files:", "  - split: train", "    path: data/train-*.parquet"]

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        return [
            "- `data/train-*.parquet`: one row per card; image columns (`original`, `cropped_left/right`, "
            "`rectified_left/right`) load as images with `datasets.load_dataset('parquet', ...)` or "
            "`load_dataset(<this folder>)`; maps are `list<list<float32>>`; typed metadata columns."
        ]

    def verify(self, root: Path, listed: dict[str, str], problems: Problems) -> None:
        """Every shard has the release schema (and its ``huggingface`` features entry); the shards
        and ``cards.jsonl`` hold the same number of cards."""
        shards = sorted(p for p in listed if p.startswith("data/") and p.endswith(".parquet"))
        if not shards:
            return
        import pyarrow.parquet as pq

        expected = parquet_schema()
        rows = 0
        for relative in shards:
            try:
                schema = pq.read_schema(root / relative)
                rows += pq.ParquetFile(root / relative).metadata.num_rows
            except Exception as exc:  # pyarrow raises several error types for a damaged file
                problems.problem(relative, f"not a readable Parquet file: {exc}")
                continue
            if not schema.equals(expected, check_metadata=False):
                problems.problem(relative, "Parquet schema differs from the release schema")
            elif (schema.metadata or {}).get(b"huggingface") != expected.metadata[b"huggingface"]:
                problems.problem(relative, "Parquet 'huggingface' features entry missing or different")
        cards_file = root / "cards.jsonl"
        if cards_file.is_file():
            with open(cards_file, "rb") as handle:
                cards = sum(1 for line in handle if line.strip())
            if cards != rows:
                problems.problem("data/", f"Parquet shards hold {rows} cards, cards.jsonl {cards}")
