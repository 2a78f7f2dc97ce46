"""``webdataset``: tar shards for the WebDataset loader, members ``<key>.<field>.<ext>``.

Byte-reproducible: USTAR members carry the release's date as their time, no owner, mode 644.
"""

from __future__ import annotations

import io
import tarfile
from dataclasses import dataclass
from typing import Any

from ..writers import CardPayload, FileLedger, encode_npy
from .base import ReleaseFormat, WriteContext
from .registry import release_format


@dataclass(frozen=True)
class WebDatasetOptions:
    cards_per_shard: int = 1000


class WebDatasetWriter:
    """``webdataset/keystone-<n>.tar`` shards; members ``<key>.<field>.<ext>`` with dot-free keys."""

    def __init__(self, ledger: FileLedger, mtime: float, cards_per_shard: int = 1000) -> None:
        self.ledger, self.mtime = ledger, int(mtime)
        self.cards_per_shard = cards_per_shard
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
        if self.tar is None or self.in_shard >= self.cards_per_shard:
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

    def summary(self) -> dict[str, Any] | None:
        return None


@release_format
class WebDatasetFormat(ReleaseFormat):
    name = "webdataset"
    description = "WebDataset tar shards: each card's record, rectified pair, disparity and depth maps as members"
    order = 30
    encodings = {".tar": "application/x-tar"}

    def default_options(self) -> WebDatasetOptions:
        return WebDatasetOptions()

    def writer(self, context: WriteContext) -> WebDatasetWriter:
        return WebDatasetWriter(context.ledger, context.date.timestamp(), self.options.cards_per_shard)

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        return [
            "- `webdataset/keystone-*.tar`: WebDataset shards; keys are the dot-free card ids, members "
            "`<id>.json`, `<id>.left.png`, `<id>.right.png`, `<id>.disparity_left.npy`, ..."
        ]
