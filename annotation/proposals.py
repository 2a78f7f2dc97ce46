"""The boxes a crop task starts from, so annotators adjust a proposal rather than draw from nothing.

One function chooses (:func:`proposed_boxes`), in this order:

1. the card's latest ``orientation`` stage result, when it is done and its metrics carry
   ``photo_left_box`` / ``photo_right_box``;
2. :func:`pipeline.photo_area.find_photo_areas` on the original, as scanned (about 0.05 s of CPU
   a card plus decoding it), remembered in memory per card id and content hash;
3. the filter's split boxes ``left_box`` / ``right_box``;
4. none: the annotator draws both boxes.

Every box is ``[x0, y0, x1, y1]`` in the original card's pixels, as scanned (the frame that
answers are stored in). A box that is not four finite numbers inside the card with positive
size is skipped, and the next source is tried: a proposal must never be refused on submit.

Those boxes are safe crops (strictly inside the photo, arches and bands cut off): what the
judge task's eye-order pictures are made from. A crop task asks for the whole photo, and
started from them every card needed four drags (on the demo cards they covered 50-80 % of the
print). So :func:`proposed_crop_boxes` grows them out to the photo's edges
(:func:`pipeline.photo_area.grow_to_photo_edges`, remembered like the photo areas): mean IoU
with the demo cards' prints 0.68 -> 0.93, with the hand-drawn boxes of the 11 real cards
0.76 -> 0.86 (``python -m benchmarks.photo_area_crowd`` has the crowd's side).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flask import current_app
from sqlalchemy import select

from core.db import db
from core.models import Card, StageResult

log = logging.getLogger(__name__)

SOURCES: tuple[str, ...] = ("orientation", "photo_area", "filter")
_CACHE_SIZE = 512  # cards; a pair of boxes is a few hundred bytes


@dataclass(frozen=True)
class ProposedBoxes:
    left: list[float]
    right: list[float]
    source: str  # one of SOURCES
    grown: bool = False  # grown out to the photo's edges (proposed_crop_boxes)

    def as_json(self) -> dict[str, Any]:
        document: dict[str, Any] = {"left": self.left, "right": self.right, "source": self.source}
        if self.grown:
            document["grown"] = True
        return document


_photo_area_cache: OrderedDict[tuple[int, str], tuple[list[float], list[float]] | None] = OrderedDict()
_grown_cache: OrderedDict[tuple[Any, ...], tuple[list[float], list[float]] | None] = OrderedDict()
_cache_lock = threading.Lock()


def _box(value: Any, width: int, height: int) -> list[float] | None:
    """``value`` as a usable box inside a ``width`` x ``height`` card, or None."""
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        return None
    try:
        x0, y0, x1, y1 = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        return None
    x0, y0, x1, y1 = max(0.0, x0), max(0.0, y0), min(float(width), x1), min(float(height), y1)
    if x1 - x0 < 1 or y1 - y0 < 1:
        return None
    return [round(x0, 1), round(y0, 1), round(x1, 1), round(y1, 1)]


def _pair(metrics: dict[str, Any] | None, left: str, right: str, card: Card) -> tuple[list[float], list[float]] | None:
    if not metrics:
        return None
    boxes = _box(metrics.get(left), card.width, card.height), _box(metrics.get(right), card.width, card.height)
    return (boxes[0], boxes[1]) if boxes[0] is not None and boxes[1] is not None else None


def _latest_metrics(card_id: int, stage: str) -> dict[str, Any] | None:
    return db.session.scalar(
        select(StageResult.metrics)
        .where(StageResult.card_id == card_id, StageResult.stage == stage, StageResult.status == "done")
        .order_by(StageResult.created_at.desc(), StageResult.id.desc())
        .limit(1)
    )


def photo_area_boxes(card: Card) -> tuple[list[float], list[float]] | None:
    """:func:`pipeline.photo_area.find_photo_areas` on the card's original, cached; None if it cannot be read."""
    key = (card.id, card.content_hash)
    with _cache_lock:
        if key in _photo_area_cache:
            _photo_area_cache.move_to_end(key)
            return _photo_area_cache[key]
    from pipeline.errors import PipelineError
    from pipeline.io import read_image
    from pipeline.photo_area import find_photo_areas

    path = Path(current_app.config["KEYSTONE_DATA_DIR"]).resolve() / card.stored_path
    try:
        areas = find_photo_areas(read_image(path))
        found: tuple[list[float], list[float]] | None = _pair(
            {"l": list(areas.left_box), "r": list(areas.right_box)}, "l", "r", card
        )
    except (OSError, ValueError, PipelineError) as exc:  # a missing or unreadable original
        log.warning("no photo areas for card %s: %s", card.id, exc)
        found = None
    with _cache_lock:
        _photo_area_cache[key] = found
        while len(_photo_area_cache) > _CACHE_SIZE:
            _photo_area_cache.popitem(last=False)
    return found


def proposed_boxes(card: Card) -> ProposedBoxes | None:
    """The boxes a crop task on ``card`` starts from, and where they came from (see the module docstring)."""
    oriented = _pair(_latest_metrics(card.id, "orientation"), "photo_left_box", "photo_right_box", card)
    if oriented is not None:
        return ProposedBoxes(*oriented, "orientation")
    found = photo_area_boxes(card)
    if found is not None:
        return ProposedBoxes(*found, "photo_area")
    split = _pair(_latest_metrics(card.id, "filter"), "left_box", "right_box", card)
    if split is not None:
        return ProposedBoxes(*split, "filter")
    return None


def _remember(cache: OrderedDict[Any, Any], key: Any, value: Any) -> None:
    with _cache_lock:
        cache[key] = value
        while len(cache) > _CACHE_SIZE:
            cache.popitem(last=False)


def proposed_crop_boxes(card: Card) -> ProposedBoxes | None:
    """The boxes a crop task on ``card`` starts from: :func:`proposed_boxes` grown out to the
    edges of the photos (see the module docstring); as proposed when the original cannot be read."""
    proposal = proposed_boxes(card)
    if proposal is None:
        return None
    key = (card.id, card.content_hash, *proposal.left, *proposal.right)
    with _cache_lock:
        cached = _grown_cache.get(key, False)
        if cached is not False:
            _grown_cache.move_to_end(key)
    if cached is False:
        from pipeline.errors import PipelineError
        from pipeline.io import read_image
        from pipeline.photo_area import grow_to_photo_edges

        path = Path(current_app.config["KEYSTONE_DATA_DIR"]).resolve() / card.stored_path
        try:
            boxes = grow_to_photo_edges(
                read_image(path),
                [tuple(round(v) for v in box) for box in (proposal.left, proposal.right)],  # type: ignore[misc]
            )
            cached = _pair({"l": list(boxes[0]), "r": list(boxes[1])}, "l", "r", card)
        except (OSError, ValueError, PipelineError) as exc:  # a missing or unreadable original
            log.warning("proposed boxes of card %s not grown: %s", card.id, exc)
            cached = None
        _remember(_grown_cache, key, cached)
    if cached is None:
        return proposal
    return ProposedBoxes(cached[0], cached[1], proposal.source, grown=True)
