"""``views``: the five GD images per card (:mod:`pipeline.views`), its cameras and a parallax
preview under ``views/<key>/``, for the cards with a finished views result (an optional component:
never a default). The cards are streamed with their views artifacts, so a card's manifest entry
carries its views digest; ``cards.jsonl`` says per card where its views are, or why it has none.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..croissant import jsonl_record_set
from ..records import VIEW_NAMES, VIEWS_FOLDER, ReleaseCard
from ..writers import CardPayload, FileLedger, encode_exr
from .base import Problems, ReleaseFormat, WriteContext
from .registry import release_format

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


# (field name, type, description) of the ``views`` record set (``views/views.jsonl``).
VIEW_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("key", "sc:Text", "The card's key (as in cards): its views are in views/<key>/."),
    ("card_id", "sc:Integer", "The card's id in the catalogue."),
    (
        "folder",
        "sc:Text",
        (
            "Folder of v0.png..v4.png (8-bit grey, or RGB for a colour card), v0_depth.exr..v4_depth.exr (float32 depth, baseline 1), "
            "views.json (cameras) and preview.webp."
        ),
    ),
    ("width", "sc:Integer", "Width of the five views in pixels."),
    ("height", "sc:Integer", "Height of the five views in pixels."),
    ("focal_px", "sc:Float", "Focal length of the reference view v0 in pixels."),
    ("quad_radius", "sc:Float", "Distance of the corner cameras v1..v4 from the quad's centre, baseline units."),
    ("preview", "sc:Text", "Path of the animated parallax preview (WebP)."),
)


class ViewsCount:
    """How many cards have views, and how many lack them for each reason (the writer's summary,
    and the dry run's count)."""

    def __init__(self) -> None:
        self.with_views = 0
        self.without: dict[str, int] = {}

    def add(self, card: ReleaseCard) -> None:
        self.add_note(card.views_note or "views not run")

    def add_note(self, note: str) -> None:
        if note == "done":
            self.with_views += 1
        else:
            self.without[note] = self.without.get(note, 0) + 1

    def as_json(self) -> dict[str, Any]:
        return {
            "cards_with_views": self.with_views,
            "cards_without_views": sum(self.without.values()),
            "without": dict(sorted(self.without.items())),
        }


class ViewsWriter:
    """``views/<key>/v0.png`` .. ``v4.png`` (8-bit grey, or RGB where the rectified view is colour;
    copied byte for byte), ``v<i>_depth.exr``
    (float32 channel ``Y``, depth along view i's -z axis, baseline 1, finite and > 0), ``views.json``
    (the cameras; its ``depth`` entries name the EXR files) and ``preview.webp`` (animated
    parallax), plus ``views/views.jsonl``, one line per card that has views. Cards without a
    finished views result are counted by reason in :attr:`count`."""

    def __init__(self, ledger: FileLedger, scratch: Path) -> None:
        self.ledger, self.scratch = ledger, scratch
        (ledger.root / VIEWS_FOLDER).mkdir(parents=True, exist_ok=True)
        (ledger.root / VIEWS_INDEX).write_bytes(b"")
        self.closed = False
        self.count = ViewsCount()

    def add(self, payload: CardPayload) -> None:
        card, views = payload.card, payload.views
        if views is None:
            self.count.add_note(card.views_note or "views not run")
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
        self.count.add_note("done")

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.ledger.record_file(VIEWS_INDEX)

    def summary(self) -> dict[str, Any]:
        return self.count.as_json()


@release_format
class ViewsFormat(ReleaseFormat):
    name = "views"
    description = "the five GD images per card with depth maps, cameras and a parallax preview"
    order = 40
    with_views = True
    reports = True

    def writer(self, context: WriteContext) -> ViewsWriter:
        return ViewsWriter(context.ledger, context.scratch)

    def plan_tally(self) -> ViewsCount:
        return ViewsCount()

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        views = summary or ViewsCount().as_json()
        return [
            f"- `views/<id>/`: the five GD images of the scene for {views['cards_with_views']} of "
            f"{views['cards_with_views'] + views['cards_without_views']} cards (the others have no finished views: "
            "graded failure, not run, or failed; `cards.jsonl` says why per card under `views`): `v0.png` (the "
            "reference view) and `v1.png`..`v4.png` (the four quad-corner views), 8-bit grey, or 8-bit RGB where "
            "the card's rectified view is in colour (`views.json` says `colour`); `v0_depth.exr`.."
            "`v4_depth.exr`, float32 channel `Y`, depth along each view's -z axis in baseline units (up to scale), "
            "finite and > 0 at every pixel (EXR as KeystoneDepth's maps); `views.json`, the five cameras (OpenGL "
            "convention, `x_cam = R x_world + t`, world = v0's camera, focal length in px, principal point at the "
            "image centre); `preview.webp`, an animated parallax preview. `views/views.jsonl` lists them."
        ]

    def changelog(self, summary: dict[str, Any] | None) -> list[str]:
        views = summary or ViewsCount().as_json()
        total = views["cards_with_views"] + views["cards_without_views"]
        lines = ["", f"### Views ({views['cards_with_views']} of {total} cards)", ""]
        lines.append(f"- {views['cards_with_views']} card(s) with the five GD images, cameras and preview under `views/`")
        lines += [f"- {count} card(s) without views: {reason}" for reason, count in views["without"].items()]
        return lines

    def record_sets(self, summary: dict[str, Any] | None, card_count: int) -> list[dict[str, Any]]:
        with_views = (summary or ViewsCount().as_json())["cards_with_views"]
        return [
            jsonl_record_set(
                "views",
                VIEW_FIELDS,
                f"The five GD images per card (reference view v0 and quad corners v1..v4, KeystoneDepth "
                f"section 5) for {with_views} of {card_count} cards; one record per card with views.",
            )
        ]

    def verify(self, root: Path, listed: dict[str, str], problems: Problems) -> None:
        """Every ``views/<key>/`` folder holds all twelve files of a card's views, and
        ``views/views.jsonl`` lists exactly those cards."""
        folders: dict[str, set[str]] = {}
        for relative in listed:
            parts = relative.split("/")
            if len(parts) == 3 and parts[0] == "views":
                folders.setdefault(parts[1], set()).add(relative)
        if not folders and VIEWS_INDEX not in listed:
            return
        for key, present in sorted(folders.items()):
            missing = sorted(set(view_files(key)) - present)
            extra = sorted(present - set(view_files(key)))
            if missing:
                problems.problem(
                    f"views/{key}/", f"incomplete views: {', '.join(p.rsplit('/', 1)[1] for p in missing)} not listed"
                )
            if extra:
                problems.problem(f"views/{key}/", f"unexpected files: {', '.join(p.rsplit('/', 1)[1] for p in extra)}")
        index = root / VIEWS_INDEX
        if VIEWS_INDEX not in listed or not index.is_file():
            problems.problem(VIEWS_INDEX, "missing: views folders are present but not indexed")
            return
        try:
            keys = [json.loads(line)["key"] for line in index.read_text().splitlines() if line.strip()]
        except (UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            problems.problem(VIEWS_INDEX, f"not one JSON record with a key per line: {exc}")
            return
        if sorted(keys) != sorted(folders):
            problems.problem(VIEWS_INDEX, f"lists {len(keys)} card(s) with views, the release has {len(folders)} views folder(s)")
