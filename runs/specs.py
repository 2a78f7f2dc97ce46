"""What the run driver knows of each stage: its spec (parameters, task, eligible cards, inputs,
readiness) and the builders of its inputs from a card's results and people's decisions."""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from core.hooks import approved_decisions, stage_params
from core.models import Card
from pipeline.contracts import DisparityInputs, GradeInputs, RectifyInputs, ViewsInputs
from pipeline.filter import FilterParams
from pipeline.records import CardTask, StageRecord
from pipeline.rectify import RectifyParams
from pipeline.stages.disparity import DisparityStageParams, disparity_task
from pipeline.stages.filter import filter_task
from pipeline.stages.orientation import OrientationStageParams, orientation_task
from pipeline.stages.rectify import rectify_task
from runs.orientation import is_decided, resolve_orientation, said_flags


@dataclass(frozen=True)
class StageSpec:
    name: str
    params: Any
    task: Callable[[CardTask], StageRecord]
    # The card states this stage applies to; other cards are not its business.
    eligible_states: tuple[str, ...]
    # What earlier stages (and approved crowd annotations) decided that this one needs.
    # The builders return the TypedDicts of pipeline.contracts (RectifyInputs, GradeInputs, ...).
    inputs: Callable[[Card, dict[str, Any]], Mapping[str, Any]] | None = None
    # The stage whose latest result must be done or skipped before this one can run.
    requires: str | None = None
    # Given a card and its inputs, whether it can run now (e.g. a card the filter sent to
    # review waits until the crowd has judged it a stereo pair).
    ready: Callable[[Card, dict[str, Any]], bool] | None = None
    # Its inputs come from the card's own stage results alone (no people's decisions), so a
    # worker may run it on a card right after the stage before it in the run (runs.chains).
    chains: bool = False


def filter_boxes(card: Card) -> dict[str, Any]:
    """The split boxes of the card's latest filter result."""
    result = card.latest_results().get("filter")
    if result is None or result.status != "done":
        return {}
    return {
        "left_box": result.metrics.get("left_box"),
        "right_box": result.metrics.get("right_box"),
        "box_source": f"filter split ({result.param_hash})",
        # The filter's SIFT matches, reused by rectification (card px, and card px per SIFT px).
        "filter_matches": result.artifacts.get("matches"),
        "filter_match_scale": result.metrics.get("match_scale"),
    }


def approved_annotations(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """People's approved decisions per card (the features register them, see
    :mod:`core.hooks`): the crowd's approved judge, confirm and crop aggregates, a
    curator's orientation override and the operator's word for the card's collection,
    ``{card: {"judge": .., "crop": .., "confirm": .., "orientation_override": .., "operator_orientation": ..}}``."""
    return approved_decisions(card_ids)


def card_orientation(card: Card, approved: dict[str, Any]) -> dict[str, Any]:
    """The orientation the pipeline uses for ``card`` (:func:`runs.orientation.resolve_orientation`)
    from its latest orientation result, approved judgement, curator override and the operator's
    word for its collection."""
    return resolve_orientation(
        card.latest_results().get("orientation"),
        approved.get("judge"),
        approved.get("orientation_override"),
        approved.get("operator_orientation"),
        confirm=approved.get("confirm"),
    )


def collection_decisions(approved: Mapping[str, Any]) -> dict[str, Any]:
    """The plain-JSON decisions about a card's whole collection that the orientation step reads:
    ``known_flags`` from an operator's word (``approved["operator_orientation"]``, a row) and
    ``upright_head`` (the refit in force, :mod:`review.upright_fit`). A chained worker has no
    database, so the driver sends it this with the card (:class:`runs.chains.ChainTask`); the
    function reads its own output back unchanged."""
    found: dict[str, Any] = {}
    known = said_flags(approved.get("operator_orientation")) or dict(approved.get("known_flags") or {})
    if known:
        found["known_flags"] = known
    if approved.get("upright_head"):
        found["upright_head"] = dict(approved["upright_head"])
    return found


def orientation_inputs(card: Card, approved: dict[str, Any]) -> dict[str, Any]:
    """What the orientation step reads: the filter's split boxes (card pixels) and what is
    known of the card's whole collection (:func:`collection_decisions`): an operator's word as
    ``known_flags`` (flag -> value) for the step to take as given, and the learned head the
    collection refitted. Without either the keys are absent, so the inputs digest of such cards
    stays what it was; a new word or refit changes it, and the step reruns."""
    boxes = filter_boxes(card)
    if not boxes:
        return {}
    return {"left_box": boxes["left_box"], "right_box": boxes["right_box"], **collection_decisions(approved)}


def photo_area_boxes(card: Card) -> dict[str, Any]:
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


def rectify_inputs(card: Card, approved: dict[str, Any]) -> RectifyInputs:
    """What rectification consumes (boxes in the original card's pixels): the crowd's consensus
    boxes where approved, else the orientation step's photo areas, else the filter's split; and
    the decided orientation (:func:`card_orientation`; null flags while undecided)."""
    inputs = filter_boxes(card)
    inputs.update(photo_area_boxes(card))
    crop = approved.get("crop")
    if crop is not None and crop.label.get("left") and crop.label.get("right"):
        inputs.update(
            left_box=[int(round(v)) for v in crop.label["left"]],
            right_box=[int(round(v)) for v in crop.label["right"]],
            box_source=f"crowd consensus (batch {crop.batch_id})",
        )
    judge = approved.get("judge")
    if judge is not None:
        inputs["is_stereo"] = bool(judge.label.get("is_stereo", True))
    orientation = card_orientation(card, approved)
    inputs.update(
        {flag: orientation[flag] for flag in ("upside_down", "inverted", "swapped")},
        orientation_decided_by=orientation["decided_by"],
        orientation_source=orientation["source"] or "undecided",
    )
    return inputs


def rectify_ready(card: Card, inputs: dict[str, Any]) -> bool:
    """Passed cards unless the crowd judged them no stereo pair; review cards once judged one;
    either only once its orientation is decided (by the step, the crowd or a curator)."""
    if not inputs.get("left_box"):
        return False
    if not is_decided(inputs):
        return False
    if card.state == "review":
        return inputs.get("is_stereo") is True
    return inputs.get("is_stereo", True) is not False


def rectified_pair(card: Card, approved: dict[str, Any]) -> DisparityInputs:
    """The rectified views, measured disparity range and focal length of the latest rectify result."""
    result = card.latest_results().get("rectify")
    if result is None or result.status not in ("done", "skipped"):
        return {}
    metrics = result.metrics
    camera = metrics.get("K") or [[None]]
    return {
        "left": result.artifacts.get("left"),
        "right": result.artifacts.get("right"),
        "disparity_range": [metrics.get("disparity_min"), metrics.get("disparity_max")],
        "focal_px": camera[0][0],
        "rectify_param_hash": result.param_hash,
    }


def grade_inputs(card: Card, approved: dict[str, Any]) -> GradeInputs:
    """What the grader measures: the rectified views, both disparity maps and their confidence
    (paths under the data dir), and the metrics of the filter, rectify and disparity results."""
    latest = card.latest_results()
    rectify, disparity = latest.get("rectify"), latest.get("disparity")
    if rectify is None or disparity is None or disparity.status != "done" or rectify.status == "failed":
        return {}
    return {
        "left": rectify.artifacts.get("left"),
        "right": rectify.artifacts.get("right"),
        "disparity_left": disparity.artifacts.get("disparity_left"),
        "disparity_right": disparity.artifacts.get("disparity_right"),
        "confidence": disparity.artifacts.get("confidence"),
        "metrics": {
            name: {k: v for k, v in result.metrics.items() if k != "inputs_digest"}
            for name, result in latest.items()
            if name in ("filter", "rectify", "disparity")
        },
        "disparity_param_hash": disparity.param_hash,
    }


def views_inputs(card: Card, approved: dict[str, Any]) -> ViewsInputs:
    """What view synthesis needs: the rectified left view, its disparity, the focal length, and
    the grade (a card graded failure gets no views)."""
    latest = card.latest_results()
    rectify, disparity, grade = latest.get("rectify"), latest.get("disparity"), latest.get("grade")
    if rectify is None or disparity is None or disparity.status != "done" or grade is None:
        return {}
    return {
        "left": rectify.artifacts.get("left"),
        "disparity_left": disparity.artifacts.get("disparity_left"),
        "focal_px": disparity.metrics.get("focal_px"),
        "grade": grade.outcome if grade.status == "done" else None,
        "grade_param_hash": grade.param_hash,
    }


# The stages ``keystone run`` can run, in flow order (judge, crop and review are people's work).
RUNNABLE_STAGES: tuple[str, ...] = ("filter", "orientation", "rectify", "disparity", "grade", "views")


def _has_inputs(card: Card, inputs: dict[str, Any]) -> bool:
    return bool(inputs)


def available_stages() -> dict[str, StageSpec]:
    """Every stage in flow order. Needs an app context: the grade thresholds come from the
    newest fitted grade model in the database (or the defaults)."""
    from pipeline.grading import GradeParams
    from pipeline.stages.grade import grade_task
    from pipeline.stages.views import views_task
    from pipeline.view_synthesis import ViewsStageParams

    filter_params, rectify_params, disparity_params = FilterParams(), RectifyParams(), DisparityStageParams()
    orientation_params = OrientationStageParams()
    grade_params = stage_params("grade", GradeParams)
    from flask import current_app

    views_params = ViewsStageParams(checkpoint=current_app.config.get("KEYSTONE_INPAINT_CHECKPOINT"))
    return {
        "filter": StageSpec(
            name="filter",
            params=filter_params,
            task=functools.partial(filter_task, params=filter_params),
            eligible_states=("ingested", "pass", "review", "culled", "failed"),
        ),
        # Every card the filter passed or sent to review: which way up, positive or negative,
        # which eye, and the photo area. A doubtful card waits for people (runs.orientation).
        "orientation": StageSpec(
            name="orientation",
            params=orientation_params,
            task=functools.partial(orientation_task, params=orientation_params),
            eligible_states=("pass", "review"),
            inputs=orientation_inputs,
            requires="filter",
            ready=_has_inputs,
            chains=True,
        ),
        # Cards the filter passed whose orientation is decided; cards in review wait for the
        # crowd's judgement too, and a culled card gets nothing.
        "rectify": StageSpec(
            name="rectify",
            params=rectify_params,
            task=functools.partial(rectify_task, params=rectify_params),
            eligible_states=("pass", "review"),
            inputs=rectify_inputs,
            ready=rectify_ready,
        ),
        # Cards whose rectification is done (or was not needed); a failed one gets no run.
        "disparity": StageSpec(
            name="disparity",
            params=disparity_params,
            task=functools.partial(disparity_task, params=disparity_params),
            eligible_states=("pass", "review"),
            inputs=rectified_pair,
            requires="rectify",
            chains=True,
        ),
        # Cards with a disparity: few / some artifacts / failure, with reasons in words.
        "grade": StageSpec(
            name="grade",
            params=grade_params,
            task=functools.partial(grade_task, params=grade_params),
            eligible_states=("pass", "review"),
            inputs=grade_inputs,
            requires="disparity",
            ready=_has_inputs,
            chains=True,
        ),
        # Optional per scene: the five GD images and a parallax preview; a failure gets none.
        "views": StageSpec(
            name="views",
            params=views_params,
            task=functools.partial(views_task, params=views_params),
            eligible_states=("pass", "review"),
            inputs=views_inputs,
            requires="grade",
            ready=_has_inputs,
            chains=True,
        ),
    }
