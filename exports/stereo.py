"""The ``stereo`` release format: each card's viewing files (anaglyph, wiggles, side-by-side, JPS,
MPO) under ``stereo/<key>/``, encoded by :mod:`pipeline.stereo_files`."""

from __future__ import annotations

import json
from typing import Any

from pipeline.stereo_files import STEREO_FORMATS, CardCaption, StereoCosts, decode_png, encode_stereo

from .records import ReleaseCard

STEREO_FOLDER = "stereo"
STEREO_INDEX = f"{STEREO_FOLDER}/stereo.jsonl"


def stereo_files(key: str) -> tuple[str, ...]:
    """Release paths of one card's stereo files, in :data:`STEREO_FORMATS` order."""
    return tuple(f"{STEREO_FOLDER}/{key}/{entry[0]}" for entry in STEREO_FORMATS.values())


class StereoWriter:
    """``stereo/<key>/`` with the seven files of :data:`STEREO_FORMATS` per card, and
    ``stereo/stereo.jsonl``, one line per card. A card whose pair cannot be encoded is counted
    in :attr:`without` with the reason (its other formats are still released)."""

    name = "stereo"

    def __init__(self, ledger: Any) -> None:
        self.ledger = ledger
        (ledger.root / STEREO_FOLDER).mkdir(parents=True, exist_ok=True)
        (ledger.root / STEREO_INDEX).write_bytes(b"")
        self.closed = False
        self.costs = StereoCosts()
        self.without: dict[str, int] = {}

    def add(self, payload: Any) -> None:
        from pipeline.stereo_formats import StereoFormatError

        card: ReleaseCard = payload.card
        caption = CardCaption.of(card.metadata, card.accession, card.source_name)
        try:
            left, right = decode_png(payload.rectified_left), decode_png(payload.rectified_right)
            files = encode_stereo(left, right, payload.disparity_left, caption, costs=self.costs)
        except (StereoFormatError, OSError, ValueError) as exc:
            reason = f"stereo files not made: {exc}"
            self.without[reason] = self.without.get(reason, 0) + 1
            return
        paths = stereo_files(card.key)
        for relative, name in zip(paths, STEREO_FORMATS):
            self.ledger.write_bytes(relative, files[name])
        line = {
            "key": card.key,
            "card_id": card.card_id,
            "folder": f"{STEREO_FOLDER}/{card.key}",
            "width": int(left.shape[1]),
            "height": int(left.shape[0]),
            "title": caption.title,
            "date": caption.date,
            "accession": caption.accession,
            "licence": caption.licence,
            **{name: relative for relative, name in zip(paths, STEREO_FORMATS)},
        }
        with open(self.ledger.root / STEREO_INDEX, "ab") as index:
            index.write(json.dumps(line, sort_keys=True, ensure_ascii=False, allow_nan=False).encode() + b"\n")

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.ledger.record_file(STEREO_INDEX)

    def summary(self) -> dict[str, Any]:
        return {
            **self.costs.as_json(),
            "cards_without": sum(self.without.values()),
            "without": dict(sorted(self.without.items())),
        }
