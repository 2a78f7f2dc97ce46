"""``keystonedepth``: KeystoneDepth's published folder layout (as third-party loaders read it),
plus the scan and the rectification of each card."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..writers import CardPayload, FileLedger, encode_exr
from .base import ReleaseFormat, WriteContext
from .registry import release_format

# KeystoneDepth's layout, plus our extra files.
KD_CROPPED = "cropped/cropped_full_LR"
KD_DISPARITY = "processed/rectified/disp_info_LR"
KD_RECTIFIED = "processed/rectified/rectified_LR"
KD_RECTIFICATION = "processed/rectified/rectification"
KD_DEPTH = "processed/depth_512"
KD_ORIGINAL = "original"


class KeystoneDepthWriter:
    """``cropped/cropped_full_LR/<id>L.png``, ``processed/rectified/disp_info_LR/<id>L.exr`` and
    the rest of the folders, one file per view and map."""

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

    def summary(self) -> dict[str, Any] | None:
        return None


@release_format
class KeystoneDepthFormat(ReleaseFormat):
    name = "keystonedepth"
    description = "KeystoneDepth's folders: cropped and rectified PNGs, EXR disparity and depth maps, the scans"
    order = 10
    default = True

    def writer(self, context: WriteContext) -> KeystoneDepthWriter:
        return KeystoneDepthWriter(context.ledger, context.scratch)

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        return [
            "- `cropped/cropped_full_LR/<id>L.png`, `<id>R.png`: the left and right views cropped from the scan "
            "(KeystoneDepth's layout; loaders written for it work).",
            "- `processed/rectified/disp_info_LR/<id>L.exr`, `<id>R.exr`: float32 disparity of the left and right "
            "rectified views, channel `Y`, pixels; `x_right = x_left - d`; NaN = unknown.",
            "- `processed/rectified/rectified_LR/<id>L.png`, `<id>R.png`: the rectified pair.",
            "- `processed/rectified/rectification/<id>.json`: `H_l`, `H_r` (3 x 3, column vectors, `x' ~ H x`, "
            "cropped view -> rectified view), `K`, `R`, `t`, crop boxes `[x0, y0, x1, y1]` in card pixels.",
            "- `processed/depth_512/<id>.exr`: depth up to scale (focal_px * baseline / d, baseline 1), 512 x 512.",
            "- `original/<id>.<ext>`: the scan as ingested (never modified).",
        ]
