"""The orientation stage task: which way up, positive or negative, which eye, and the photo area.

Runs on every card the filter passed or sent to review, before rectification. It measures the
card as scanned (:func:`pipeline.orientation.estimate_orientation` on the filter's split boxes)
and finds each photo inside its mount (:func:`pipeline.photo_area.find_photo_areas`). The
record's ``outcome`` is the decision: ``auto`` when the most probable combination of the three
flags is confident (the flow applies it to derived images), ``ask`` when people must look (the
card waits in the crowd's judge queue). :mod:`pipeline.decided_orientation` turns that, the
crowd's judgement and any curator override into the orientation the pipeline uses.

Metrics (all JSON):

* ``flags``: per flag ``{"p": P(flag set), "decided": bool, "value": bool | None,
  "evidence": [cue meanings in words, strongest first]}``;
* ``decision`` (``auto`` / ``ask``), ``confidence`` (the least confident flag's probability of
  its value), ``combination_probability``, ``undecidable`` (why nothing can be said, or null);
* ``same_turn_and_swap`` / ``tie_decided``: P(upside_down == swapped) and whether it is
  confident, so one answer from people about the turn settles the eye order too;
* ``photo_left_box`` / ``photo_right_box``: ``[x0, y0, x1, y1]`` in the ORIGINAL card's pixels
  as scanned (x1/y1 exclusive), ``photo_area_source`` in words, ``photo_area_confidence``,
  ``photo_area_fallback`` (the reason the split's boxes were kept, or null) and its evidence;
* ``seconds_orientation`` / ``seconds_photo_area``: CPU cost of each part.

Degenerate cards never get a silent guess: a contract break (tiny card, box outside it) is a
typed ``failed`` record (the wrapper), a blank, identical or three-photo card is ``ask`` with
``undecidable`` saying why.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..decided_orientation import said_flags
from ..errors import PipelineError
from ..io import read_image_reduced
from ..orientation import (
    FLAGS,
    OrientationEstimate,
    OrientationParams,
    estimate_orientation,
)
from ..photo_area import PhotoAreaParams, PhotoAreas, find_photo_areas
from ..records import CardTask
from ..results import CardResults
from ..upright import write_learned_differences
from .base import StageOutput, stage_task
from .filter import filter_boxes
from .spec import StageDeclaration, has_inputs

__all__ = [
    "STAGE",
    "OrientationStageParams",
    "collection_decisions",
    "orientation_inputs",
    "orientation_metrics",
    "orientation_task",
    "photo_area_boxes",
]


@dataclass(frozen=True)
class OrientationStageParams:
    """Parameters of the orientation stage: the estimator's and the photo-area finder's."""

    orientation: OrientationParams = field(default_factory=OrientationParams)
    photo_area: PhotoAreaParams = field(default_factory=PhotoAreaParams)
    decode_min_width: int = 1200
    """px: a JPEG scan is decoded at the largest reduction (1/2, 1/4, 1/8) that keeps it at least
    this wide (every cue works on a smaller copy: photos at 512 px, print at 1024, photo areas at
    480), and the boxes are mapped both ways. 0 decodes at full size."""


def _flag_words(estimate: OrientationEstimate, flag: str) -> list[str]:
    # Every weighted cue that sees the flag, the silent ones too ("greyscale scan: no colour
    # evidence" says why a flag stayed doubtful).
    cues = [cue for cue in getattr(estimate, flag).evidence if cue.weight > 0]
    cues.sort(key=lambda cue: -abs(cue.weight * cue.value))
    return [f"{cue.name}: {cue.meaning} ({cue.value:+.2f} x {cue.weight:g})" for cue in cues]


def orientation_metrics(estimate: OrientationEstimate, areas: PhotoAreas | None) -> dict[str, Any]:
    """The stage's metrics from an estimate and the photo areas (see the module docstring)."""
    flags: dict[str, Any] = {}
    for flag in FLAGS:
        one = getattr(estimate, flag)
        words = _flag_words(estimate, flag) if estimate.undecidable is None else [estimate.undecidable]
        flags[flag] = {
            "p": round(one.probability, 4),
            "decided": bool(one.decided and estimate.undecidable is None),
            "value": one.value if estimate.undecidable is None else None,
            "evidence": words,
        }
    metrics: dict[str, Any] = {
        "flags": flags,
        "decision": estimate.decision,
        # the most probable flags, what a confirmation grid shows (null when undecidable)
        "proposed": estimate.proposed_orientation(),
        "known_flags": estimate.known or None,
        "learned": estimate.details.get("learned"),
        # every cue's value: what a refit of the learned head re-decides from (review.upright_fit)
        "cue_values": {cue.name: round(cue.value, 4) for cue in estimate.cues},
        "confidence": round(estimate.confidence, 4),
        "combination_probability": round(estimate.combination_probability, 4),
        "same_turn_and_swap": round(estimate.same_turn_and_swap, 4),
        "tie_decided": bool(estimate.tie_decided and estimate.undecidable is None),
        "undecidable": estimate.undecidable,
        "seconds_orientation": round(estimate.seconds, 4),
        # what the printed-text cue read (lines, both readings), or why it did not read
        "text": estimate.details.get("text"),
    }
    if areas is not None:
        metrics.update(
            photo_left_box=[int(v) for v in areas.left_box],
            photo_right_box=[int(v) for v in areas.right_box],
            photo_area_confidence=areas.confidence,
            photo_area_fallback=areas.fallback_reason,
            photo_area_evidence=list(areas.evidence),
            photo_area_source=(
                f"photo area (confidence {areas.confidence:.2f})"
                if not areas.is_fallback
                else f"filter split kept by the photo-area finder: {areas.fallback_reason}"
            ),
        )
    return metrics


def _reason(metrics: dict[str, Any]) -> str:
    if metrics["undecidable"]:
        return f"asking people: {metrics['undecidable']}"
    words = []
    for flag, info in metrics["flags"].items():
        state = "yes" if info["value"] else "no" if info["value"] is False else "?"
        words.append(f"{flag} {state} (P {info['p']:.2f})")
    verdict = {
        "auto": "decided automatically",
        "confirm": "asking people to confirm the most probable orientation",
    }.get(metrics["decision"], "asking people")
    return f"{verdict}: " + ", ".join(words)


def _scaled_areas(areas: PhotoAreas, scale: tuple[float, float], shape: tuple[int, int]) -> PhotoAreas:
    """Photo areas found on the estimator's working copy, in the scan's pixels (rounded inwards)."""
    sx, sy = scale
    height, width = shape

    def scaled(box: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        x0, y0 = min(width - 1, math.ceil(box[0] * sx)), min(height - 1, math.ceil(box[1] * sy))
        return (x0, y0, max(x0 + 1, min(width, math.floor(box[2] * sx))), max(y0 + 1, min(height, math.floor(box[3] * sy))))

    return replace(areas, left_box=scaled(areas.left_box), right_box=scaled(areas.right_box), gutter_x=round(areas.gutter_x * sx))


def _to_decoded(box: Any, to_scan: tuple[float, float], shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """A box in the scan's px as a box in the decoded copy's px (grown outwards, kept inside)."""
    x0, y0, x1, y1 = (float(v) for v in box)
    height, width = shape
    return (
        max(0, math.floor(x0 / to_scan[0])),
        max(0, math.floor(y0 / to_scan[1])),
        min(width, math.ceil(x1 / to_scan[0])),
        min(height, math.ceil(y1 / to_scan[1])),
    )


@stage_task("orientation")
def orientation_task(task: CardTask, params: OrientationStageParams) -> StageOutput:
    """Estimate the card's orientation on the filter's split boxes and find its photo areas.

    ``task.inputs`` must hold the filter's ``left_box`` and ``right_box`` (card pixels).
    """
    boxes = task.inputs.get("left_box"), task.inputs.get("right_box")
    if boxes[0] is None or boxes[1] is None:
        raise PipelineError("no split boxes from the filter stage; run the filter first")
    keep = params.decode_min_width if params.decode_min_width > 0 else 10**9  # 0: no reduction
    decoded = read_image_reduced(task.image_path, (keep, 0))
    card, (full_width, full_height) = decoded.pixels, decoded.full_size
    # the scan's px per decoded px, along x and y (1.0 at full size)
    to_scan = (full_width / card.shape[1], full_height / card.shape[0])
    known = task.inputs.get("known_flags") or None
    orientation_params = params.orientation
    head = task.inputs.get("upright_head")
    if head:  # a collection's refit (keystone orientation fit): a path under the data dir
        orientation_params = replace(
            orientation_params, learned_head=str(Path(task.data_dir) / head["path"]), learned_head_version=str(head["version"])
        )
    estimate = estimate_orientation(
        card,
        _to_decoded(boxes[0], to_scan, card.shape[:2]),
        _to_decoded(boxes[1], to_scan, card.shape[:2]),
        orientation_params,
        known=known,
    )
    clock = time.perf_counter()
    found = estimate.photo_areas
    reused = (
        found is not None
        and params.orientation.arch_working_width == params.photo_area.working_width
        and params.photo_area == type(params.photo_area)(working_width=params.photo_area.working_width)
    )
    if found is not None and reused:
        # The estimator's arched-top cue found them already, on a negative read as a positive
        # (measured: the photo-area finder misses more boxes on negatives as scanned).
        scale = (estimate.photo_areas_scale[0] * to_scan[0], estimate.photo_areas_scale[1] * to_scan[1])
        areas = _scaled_areas(found, scale, (full_height, full_width))
    else:
        areas = find_photo_areas(255 - card if estimate.inverted.value else card, params.photo_area)
        if decoded.factor > 1:
            areas = _scaled_areas(areas, to_scan, (full_height, full_width))
    metrics = orientation_metrics(estimate, areas)
    metrics["photo_area_read_as_positive"] = bool(estimate.photo_areas_inverted if reused else estimate.inverted.value)
    metrics["seconds_photo_area"] = round(time.perf_counter() - clock, 4)
    metrics["card_size"] = [int(full_width), int(full_height)]
    metrics["decode_factor"] = decoded.factor
    artifacts = {}
    if estimate.learned_differences:
        # The learned heads' inputs, so `keystone orientation fit` can refit the head on the
        # collection's decided cards without running the network again (float16: ~15 KB a card).
        path = write_learned_differences(Path(task.work_dir) / "upright_differences.npz", estimate.learned_differences)
        artifacts["upright_differences"] = str(path.relative_to(task.data_dir))
    return StageOutput(outcome=metrics["decision"], reason=_reason(metrics), metrics=metrics, artifacts=artifacts)


def collection_decisions(approved: Mapping[str, Any]) -> dict[str, Any]:
    """The plain-JSON decisions about a card's whole collection that the orientation step reads:
    ``known_flags`` from an operator's word (``approved["operator_orientation"]``, a row) and
    ``upright_head`` (the refit in force, :mod:`review.upright_fit`). A chained worker has no
    database, so the driver sends it this with the card (:class:`pipeline.chains.ChainTask`); the
    function reads its own output back unchanged."""
    found: dict[str, Any] = {}
    known = said_flags(approved.get("operator_orientation")) or dict(approved.get("known_flags") or {})
    if known:
        found["known_flags"] = known
    if approved.get("upright_head"):
        found["upright_head"] = dict(approved["upright_head"])
    return found


def orientation_inputs(card: CardResults, approved: Mapping[str, Any]) -> dict[str, Any]:
    """What the orientation step reads: the filter's split boxes (card pixels) and what is
    known of the card's whole collection (:func:`collection_decisions`): an operator's word as
    ``known_flags`` (flag -> value) for the step to take as given, and the learned head the
    collection refitted. Without either the keys are absent, so the inputs digest of such cards
    stays what it was; a new word or refit changes it, and the step reruns."""
    boxes = filter_boxes(card)
    if not boxes:
        return {}
    return {"left_box": boxes["left_box"], "right_box": boxes["right_box"], **collection_decisions(approved)}


def photo_area_boxes(card: CardResults) -> dict[str, Any]:
    """The orientation step's photo-area boxes (original card pixels), unless the finder fell
    back to the split."""
    result = card.latest_results().get("orientation")
    if result is None or result.status != "done":
        return {}
    metrics = result.metrics
    if metrics.get("photo_area_fallback") or not metrics.get("photo_left_box") or not metrics.get("photo_right_box"):
        return {}
    return {
        "left_box": metrics["photo_left_box"],
        "right_box": metrics["photo_right_box"],
        "box_source": f"photo area ({result.param_hash}, confidence {metrics.get('photo_area_confidence')})",
    }


# Every card the filter passed or sent to review: which way up, positive or negative, which eye,
# and the photo area. A doubtful card waits for people (pipeline.decided_orientation).
STAGE = StageDeclaration(
    name="orientation",
    position=20,
    params=OrientationStageParams,
    task=orientation_task,
    eligible_states=("pass", "review"),
    inputs=orientation_inputs,
    requires="filter",
    ready=has_inputs,
    chains=True,
    plain_decisions=collection_decisions,
)
