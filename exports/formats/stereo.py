"""``stereo``: each card's viewing files (anaglyph, wiggles, side-by-side, JPS, MPO) under
``stereo/<key>/``, encoded by :mod:`pipeline.stereo_files` with the card's title, date, accession
and licence in each file (an optional component: never a default)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.stereo_files import STEREO_FORMATS, CardCaption, StereoCosts, decode_png, encode_stereo
from pipeline.stereo_formats import StereoFormatError

from ..croissant import jsonl_record_set
from ..writers import CardPayload, FileLedger
from .base import Problems, ReleaseFormat, WriteContext
from .registry import release_format

STEREO_FOLDER = "stereo"
STEREO_INDEX = f"{STEREO_FOLDER}/stereo.jsonl"


def stereo_files(key: str) -> tuple[str, ...]:
    """Release paths of one card's stereo files, in :data:`STEREO_FORMATS` order."""
    return tuple(f"{STEREO_FOLDER}/{key}/{entry[0]}" for entry in STEREO_FORMATS.values())


# (field name, type, description) of the ``stereo`` record set (``stereo/stereo.jsonl``).
STEREO_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("key", "sc:Text", "The card's key (as in cards): its stereo files are in stereo/<key>/."),
    ("card_id", "sc:Integer", "The card's id in the catalogue."),
    ("width", "sc:Integer", "Width of one rectified view in pixels."),
    ("height", "sc:Integer", "Height of one rectified view in pixels."),
    ("anaglyph", "sc:Text", "Path of the red-cyan anaglyph (JPEG, Dubois least squares)."),
    ("wiggle_gif", "sc:Text", "Path of the animated wiggle (GIF), in-between views synthesised from the disparity."),
    ("wiggle_webp", "sc:Text", "Path of the animated wiggle (WebP)."),
    ("sbs_full", "sc:Text", "Path of the full side-by-side image, parallel (left view on the left)."),
    ("sbs_half", "sc:Text", "Path of the half side-by-side image, parallel, each view at half width."),
    ("jps", "sc:Text", "Path of the JPS file, cross-eyed (right view on the left)."),
    ("mpo", "sc:Text", "Path of the MPO file, left view first."),
)


class StereoWriter:
    """``stereo/<key>/`` with the seven files of :data:`STEREO_FORMATS` per card, and
    ``stereo/stereo.jsonl``, one line per card. A card whose pair cannot be encoded is counted
    in :attr:`without` with the reason (its other formats are still released)."""

    def __init__(self, ledger: FileLedger) -> None:
        self.ledger = ledger
        (ledger.root / STEREO_FOLDER).mkdir(parents=True, exist_ok=True)
        (ledger.root / STEREO_INDEX).write_bytes(b"")
        self.closed = False
        self.costs = StereoCosts()
        self.without: dict[str, int] = {}

    def add(self, payload: CardPayload) -> None:
        card = payload.card
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


@release_format
class StereoFormat(ReleaseFormat):
    name = "stereo"
    description = "viewing files per card: anaglyph, wiggle GIF and WebP, side-by-side, JPS and MPO"
    order = 50
    encodings = {".mpo": "image/mpo", ".jps": "image/x-jps"}
    reports = True

    def writer(self, context: WriteContext) -> StereoWriter:
        return StereoWriter(context.ledger)

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        cards = (summary or {}).get("cards", 0)
        return [
            f"- `stereo/<id>/`: viewing files of the rectified pair for {cards} cards: `anaglyph.jpg` "
            "(red-cyan, Dubois least-squares matrices, red filter on the left eye), `wiggle.gif` and `wiggle.webp` "
            "(a looping sweep from the left view to the right one and back, in-between views synthesised by warping "
            "the left view by a fraction of the disparity), `sbs_full.jpg` and `sbs_half.jpg` (parallel side-by-side: "
            "left view on the left; half = each view squeezed to half width, for 3D TVs and headsets), `cross.jps` "
            "(JPS: cross-eyed, right view on the left) and `pair.mpo` (multi-picture JPEG, left view first, for 3D "
            "displays and cameras). Each carries the card's title, date, accession and licence (EXIF and XMP; "
            "the GIF's comment). `stereo/stereo.jsonl` lists them."
        ]

    def changelog(self, summary: dict[str, Any] | None) -> list[str]:
        stereo = summary or {"cards": 0, "cards_without": 0, "without": {}}
        total = stereo["cards"] + stereo["cards_without"]
        lines = ["", f"### Stereo files ({stereo['cards']} of {total} cards)", ""]
        lines.append(f"- {stereo['cards']} card(s) with an anaglyph, two wiggles, side-by-side, JPS and MPO under `stereo/`")
        lines += [f"- {count} card(s) without: {reason}" for reason, count in stereo["without"].items()]
        return lines

    def record_sets(self, summary: dict[str, Any] | None, card_count: int) -> list[dict[str, Any]]:
        cards = (summary or {}).get("cards", 0)
        return [
            jsonl_record_set(
                "stereo",
                STEREO_FIELDS,
                f"Viewing files of the rectified pair (anaglyph, wiggles, side-by-side, JPS, MPO) for "
                f"{cards} of {card_count} cards; one record per card with them.",
            )
        ]

    def verify(self, root: Path, listed: dict[str, str], problems: Problems) -> None:
        """Every ``stereo/<key>/`` folder holds the seven stereo files, ``stereo/stereo.jsonl`` lists
        exactly those cards, each MPO opens with two frames of one size and each JPS is an
        even-width image."""
        folders: dict[str, set[str]] = {}
        for relative in listed:
            parts = relative.split("/")
            if len(parts) == 3 and parts[0] == STEREO_FOLDER:
                folders.setdefault(parts[1], set()).add(relative)
        if not folders and STEREO_INDEX not in listed:
            return
        for key, present in sorted(folders.items()):
            expected = set(stereo_files(key))
            missing, extra = sorted(expected - present), sorted(present - expected)
            if missing:
                problems.problem(f"stereo/{key}/", f"incomplete: {', '.join(p.rsplit('/', 1)[1] for p in missing)} not listed")
            if extra:
                problems.problem(f"stereo/{key}/", f"unexpected files: {', '.join(p.rsplit('/', 1)[1] for p in extra)}")
            for relative in sorted(present & expected):
                if relative.endswith((".mpo", ".jps")) and (root / relative).is_file():
                    _check_stereo_image(root / relative, relative, problems)
        index = root / STEREO_INDEX
        if STEREO_INDEX not in listed or not index.is_file():
            problems.problem(STEREO_INDEX, "missing: stereo folders are present but not indexed")
            return
        try:
            keys = [json.loads(line)["key"] for line in index.read_text().splitlines() if line.strip()]
        except (UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            problems.problem(STEREO_INDEX, f"not one JSON record with a key per line: {exc}")
            return
        if sorted(keys) != sorted(folders):
            problems.problem(STEREO_INDEX, f"lists {len(keys)} card(s), the release has {len(folders)} stereo folder(s)")


def _check_stereo_image(path: Path, relative: str, problems: Problems) -> None:
    """An MPO must hold two frames of one size; a JPS must be an even-width image."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            if relative.endswith(".mpo"):
                frames = getattr(image, "n_frames", 1)
                if image.format != "MPO" or frames != 2:
                    problems.problem(relative, f"expected an MPO with 2 frames, got {image.format} with {frames}")
                    return
                size = image.size
                image.seek(1)
                if image.size != size:
                    problems.problem(relative, f"the MPO's frames differ in size: {size} and {image.size}")
            elif image.width % 2:
                problems.problem(relative, f"a JPS holds two views side by side: odd width {image.width}")
    except (OSError, UnidentifiedImageError, SyntaxError) as exc:
        problems.problem(relative, f"not a readable image: {exc}")
