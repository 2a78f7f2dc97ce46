"""The driver: choose the cards a stage still owes, run them through an executor, write results.

Workers only compute and return :class:`pipeline.records.StageRecord`; this module alone
writes to the database, in batches, so a crash costs only the cards in flight and the
uncommitted batch. Rerunning skips every card that already has a ``done`` or ``skipped``
result for the same stage and parameters; ``failed`` cards are retried.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Executor
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import click
from flask.cli import with_appcontext
from sqlalchemy import exists, func, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import selectinload

from core.db import db, one_writer, utcnow
from core.hooks import after_write, approved_decisions, people_work, stage_params
from core.models import CARD_STATES, Card, StageResult
from pipeline.contracts import DisparityInputs, GradeInputs, RectifyInputs, ViewsInputs
from pipeline.filter import FilterParams
from pipeline.records import STAGES, CardTask, StageRecord, param_hash
from pipeline.rectify import RectifyParams
from pipeline.runner import RestartingProcessPool, init_worker, run_tasks
from pipeline.stages.disparity import DisparityStageParams, disparity_task
from pipeline.stages.filter import filter_task
from pipeline.stages.orientation import OrientationStageParams, orientation_task
from pipeline.stages.rectify import rectify_task
from runs.chains import ChainOutcome, ChainTask, ResultView, run_chain
from runs.claims import DEFAULT_CLAIM_BATCH, DEFAULT_CLAIM_TTL_S, Driver, result_fingerprint
from runs.orientation import is_decided, public_orientation, resolve_orientation, said_flags

WRITE_BATCH = 50
WRITE_INTERVAL_S = 2.0
# How often a run waiting for cards another run holds looks again (at most; a quarter of the
# claim lifetime when that is shorter).
WAIT_POLL_S = 2.0
# `keystone run` exit status when --no-wait left cards that another run holds.
EXIT_HELD = 3


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


@dataclass
class StageReport:
    stage: str
    param_hash: str
    processed: int = 0
    skipped_existing: int = 0
    done: int = 0
    failed: int = 0
    outcomes: dict[str, int] = field(default_factory=dict)
    failures: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    # Concurrent runs (see runs.claims): cards another live run held when this one reached them,
    # of those (or any) the ones another run finished meanwhile, the ones still held when this
    # run gave up on them (--no-wait), and lapsed claims of a dead run this one took over.
    held_by_other_run: int = 0
    done_by_other_run: int = 0
    still_held: int = 0
    taken_over: int = 0
    held_by: set[str] = field(default_factory=set)
    # Of ``processed``, the cards a worker ran through this stage straight after the stage
    # before it (runs.chains); and the reports of the stages chained after this one.
    chained: int = 0
    chained_cards: list[int] = field(default_factory=list)
    followers: dict[str, StageReport] = field(default_factory=dict)
    # The orientation step's decisions this run changed on cards it had decided before (a
    # collection's refitted head, an operator's word): card, before, after (decided_changes).
    changed_decisions: list[dict[str, Any]] = field(default_factory=list)

    def absorb(self, chained: StageReport) -> None:
        """Count what a chain led by an earlier stage computed for this stage: those cards were
        planned as already done when this stage ran after it."""
        self.processed += chained.processed
        self.done += chained.done
        self.failed += chained.failed
        self.chained += chained.chained
        self.chained_cards.extend(chained.chained_cards)
        self.failures.extend(chained.failures)
        self.changed_decisions.extend(chained.changed_decisions)
        for outcome, count in chained.outcomes.items():
            self.outcomes[outcome] = self.outcomes.get(outcome, 0) + count
        self.skipped_existing = max(0, self.skipped_existing - chained.done)
        self.seconds += chained.seconds

    def as_json(self) -> dict[str, Any]:
        extra = {"changed_decisions": self.changed_decisions} if self.stage == "orientation" else {}
        return {
            **extra,
            "stage": self.stage,
            "param_hash": self.param_hash,
            "processed": self.processed,
            "already_done": self.skipped_existing,
            "done": self.done,
            "failed": self.failed,
            "outcomes": self.outcomes,
            "failures": self.failures,
            "held_by_other_run": self.held_by_other_run,
            "done_by_other_run": self.done_by_other_run,
            "still_held": self.still_held,
            "taken_over": self.taken_over,
            "chained": self.chained,
            "seconds": round(self.seconds, 3),
            "cards_per_second": round(self.processed / self.seconds, 3) if self.seconds > 0 else None,
        }


def card_work_dir(data_dir: Path, content_hash: str, stage: str, phash: str) -> Path:
    """Artifacts are keyed by card content and stage parameters, never by database id."""
    return data_dir / "derived" / content_hash[:2] / content_hash / stage / phash


@contextmanager
def make_executor(kind: str, workers: int, scheduler: str | None) -> Iterator[Executor | None]:
    if kind == "dask":
        try:
            from distributed import Client
        except ImportError as exc:
            raise RuntimeError("the dask executor needs dask.distributed: pip install 'dask[distributed]'") from exc
        from pipeline.dask_worker import OneThreadWorkerPlugin

        client = Client(scheduler) if scheduler else Client(n_workers=workers, threads_per_worker=1, processes=True)
        try:
            # Every worker, those that join later too, gets what a local pool worker gets.
            client.register_plugin(OneThreadWorkerPlugin())
            yield client.get_executor()
        finally:
            client.close()
    elif kind == "local":
        if workers <= 1:
            # Inline: this process is the one worker, and gets a pool worker's set-up (one
            # OpenCV and BLAS thread, freed memory kept): `--workers 1` uses one core, and the
            # kernel does not zero the same pages for every card (measured on 42 cards: system
            # CPU 5.05 -> ~1.1 s, docs/SCALE.md).
            init_worker()
            yield None
            return
        with RestartingProcessPool(workers) as pool:
            yield pool
    else:
        raise ValueError(f"unknown executor {kind!r}; expected local or dask")


def inputs_digest(inputs: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:16]


PLAN_CHUNK = 500  # cards read and planned per step (and ids per IN list, under SQLite's bound-parameter
# limit): memory stays flat at any catalogue size


@dataclass(frozen=True)
class PlannedCard:
    """A card a stage still has to compute, with what the run needs to send it out: its inputs
    and the fingerprint of the result row it may replace (``None`` when there is none)."""

    card_id: int
    content_hash: str
    stored_path: str
    inputs: dict[str, Any]
    fingerprint: Any


def pending_cards(spec: StageSpec, phash: str, chunk: int = PLAN_CHUNK) -> tuple[list[PlannedCard], int]:
    """Cards that still need ``spec`` with these parameters (with their inputs), and how many
    are already finished. A finished card runs again when its inputs changed (say the crowd's
    boxes arrived after the automatic split was used).

    A stage without inputs is planned in SQL (cards with no finished result for this parameter
    hash); a stage with inputs reads the eligible card ids in one query, then the cards in chunks of ``chunk`` by id,
    computes each card's inputs and lets the chunk's rows go, so planning never holds the whole
    catalogue in memory.
    """
    eligible = Card.state.in_(spec.eligible_states)
    if spec.requires is not None:
        eligible = eligible & exists().where(
            StageResult.card_id == Card.id,
            StageResult.stage == spec.requires,
            StageResult.status.in_(("done", "skipped")),
        )
    already = 0
    if spec.inputs is None:
        finished = exists().where(
            StageResult.card_id == Card.id,
            StageResult.stage == spec.name,
            StageResult.param_hash == phash,
            StageResult.status.in_(("done", "skipped")),
        )
        already = db.session.scalar(select(func.count()).select_from(Card).where(eligible, finished)) or 0
        eligible = eligible & ~finished
        if spec.ready is None:
            # Nothing to compute per card: the plan is one query over plain columns, with the
            # row a result would replace (a failed one) joined in.
            own = StageResult.__table__.alias("own")
            rows = db.session.execute(
                select(Card.id, Card.content_hash, Card.stored_path, own.c.status, own.c.started_at)
                .outerjoin(own, (own.c.card_id == Card.id) & (own.c.stage == spec.name) & (own.c.param_hash == phash))
                .where(eligible)
                .order_by(Card.id)
            )
            return [
                PlannedCard(
                    card_id, content_hash, stored_path, {}, None if status is None else result_fingerprint(status, started_at)
                )
                for card_id, content_hash, stored_path, status, started_at in rows
            ], already
    todo: list[PlannedCard] = []
    # The eligible ids in one query (a few MB at 250,000 cards), then the cards chunk by chunk
    # by id. Paging the eligible query itself (``id > after LIMIT chunk``) let PostgreSQL
    # re-evaluate the ``requires`` semi-join over every stage result for every chunk, which
    # grew with the square of the catalogue.
    eligible_ids = list(db.session.scalars(select(Card.id).where(eligible).order_by(Card.id)))
    for start in range(0, len(eligible_ids), chunk):
        cards = list(
            db.session.scalars(
                select(Card)
                .where(Card.id.in_(eligible_ids[start : start + chunk]))
                .order_by(Card.id)
                .options(selectinload(Card.stage_results))
            )
        )
        approved = approved_decisions([card.id for card in cards]) if spec.inputs is not None else {}
        for card in cards:
            inputs = spec.inputs(card, approved.get(card.id, {})) if spec.inputs is not None else {}
            if spec.ready is not None and not spec.ready(card, inputs):
                continue
            own = next((r for r in card.stage_results if r.stage == spec.name and r.param_hash == phash), None)
            if (
                own is not None
                and own.status in ("done", "skipped")
                and (spec.inputs is None or own.metrics.get("inputs_digest") == inputs_digest(inputs))
            ):
                already += 1
                continue
            todo.append(
                PlannedCard(
                    card.id,
                    card.content_hash,
                    card.stored_path,
                    inputs,
                    None if own is None else result_fingerprint(own.status, own.started_at),
                )
            )
        db.session.expunge_all()  # this chunk is planned: let its cards and results go
    return todo, already


def run_stage(
    spec: StageSpec,
    *,
    data_dir: Path,
    executor: Executor | None,
    on_start: Callable[[int], None] | None = None,
    on_record: Callable[[StageRecord], None] | None = None,
    driver: Driver | None = None,
    wait_for_held: bool = True,
    claim_batch: int = DEFAULT_CLAIM_BATCH,
    on_wait: Callable[[int, set[str]], None] | None = None,
    followers: Sequence[StageSpec] = (),
    leave_out: Mapping[str, set[int]] | None = None,
) -> StageReport:
    """Run one stage over the cards that still need it, claiming each card before computing it.

    Cards another live run holds are skipped in the first pass; afterwards, with
    ``wait_for_held``, the run polls for them until that run finishes them (they are then
    counted as ``done_by_other_run``) or its claims lapse (this run takes them over). Without
    it they are left and counted as ``still_held``. ``driver`` is this run's claim identity;
    without one the stage runs under a fresh one of its own.

    ``followers``: stages (each with ``chains``) that a worker runs on each card straight after
    this one where the card qualifies (:mod:`runs.chains`); their records are written here and
    counted in ``report.followers``. Run each follower afterwards as usual, with
    ``leave_out={stage: cards this run computed for it}``: it picks up what the chains did not
    reach, and a card a chain failed is not retried in the same run.
    """
    if driver is None:
        with Driver(db.engine).running() as own:
            return run_stage(
                spec,
                data_dir=data_dir,
                executor=executor,
                on_start=on_start,
                on_record=on_record,
                driver=own,
                wait_for_held=wait_for_held,
                claim_batch=claim_batch,
                on_wait=on_wait,
                followers=followers,
                leave_out=leave_out,
            )
    if any(not follower.chains for follower in followers):
        raise ValueError(f"only stages whose inputs are stage results can be chained: {[f.name for f in followers]}")
    phash = param_hash(spec.params)
    report = StageReport(stage=spec.name, param_hash=phash)
    cards, report.skipped_existing = pending_cards(spec, phash)
    skip = (leave_out or {}).get(spec.name, set())
    cards = [card for card in cards if card.card_id not in skip]
    seen = {card.card_id: card.fingerprint for card in cards}
    tasks = {
        card.card_id: CardTask(
            card_id=card.card_id,
            content_hash=card.content_hash,
            image_path=str(data_dir / card.stored_path),
            work_dir=str(card_work_dir(data_dir, card.content_hash, spec.name, phash)),
            data_dir=str(data_dir),
            inputs=card.inputs,
        )
        for card in cards
    }
    del cards
    digests = {task.card_id: inputs_digest(task.inputs) for task in tasks.values() if spec.inputs is not None}
    db.session.commit()  # release the read transaction while workers compute
    if on_start is not None:
        on_start(len(tasks))

    clock = time.perf_counter()
    computed: list[int] = []
    held: dict[int, str] = {}
    chain = _Chain(spec, followers, driver) if followers else None
    if chain is not None:
        report.followers = chain.reports
    function: Callable[[Any], Any] = spec.task if chain is None else chain.function

    def claimed_tasks(card_ids: list[int]) -> Iterator[CardTask | ChainTask]:
        # Claimed a batch at a time, just before the executor wants them, so a second run
        # finds the cards this one has not reached yet.
        for start in range(0, len(card_ids), claim_batch):
            batch_ids = card_ids[start : start + claim_batch]
            claim = driver.claim(spec.name, phash, batch_ids, seen)
            report.taken_over += len(claim.taken_over)
            report.done_by_other_run += len(claim.finished_elsewhere)
            for card_id in batch_ids:
                held.pop(card_id, None)
            held.update(claim.held)
            if chain is None:
                for card_id in claim.claimed:
                    yield tasks[card_id]
            else:
                yield from chain.tasks([tasks[card_id] for card_id in claim.claimed])

    def compute(card_ids: list[int]) -> None:
        batch: list[StageRecord] = []
        last_write = time.monotonic()
        for item in run_tasks(function, claimed_tasks(card_ids), executor, stage=spec.name, param_hash=phash):
            record = item if chain is None else chain.take(item)
            batch.append(record)
            computed.append(record.card_id)
            _count(report, record)
            if on_record is not None:
                on_record(record)
            if len(batch) >= WRITE_BATCH or time.monotonic() - last_write > WRITE_INTERVAL_S:
                report.changed_decisions += write_records(batch, digests, driver)
                if chain is not None:
                    chain.write()
                batch, last_write = [], time.monotonic()
        if batch:
            report.changed_decisions += write_records(batch, digests, driver)
        if chain is not None:
            chain.write()

    compute(list(tasks))
    report.held_by_other_run = len(held)
    report.held_by = set(held.values())
    poll_s = min(WAIT_POLL_S, driver.ttl_s / 4)
    while held and wait_for_held:
        if on_wait is not None:
            on_wait(len(held), set(held.values()))
        time.sleep(poll_s)
        compute(sorted(held))
    report.still_held = len(held)
    if computed:
        # What must follow a write (review: new automatic grades reach the curators' queue).
        after_write(spec.name, computed)
    if chain is not None:
        for follower in followers:
            if chain.reports[follower.name].chained_cards:
                after_write(follower.name, chain.reports[follower.name].chained_cards)
    report.seconds = time.perf_counter() - clock
    return report


class _Chain:
    """The driver's side of chained stages (:mod:`runs.chains`) for one lead stage: claims the
    followers with the lead, sends each card's snapshot along, writes what the chains made
    after the lead's records of the same batch, and frees the claims a chain did not use."""

    def __init__(self, lead: StageSpec, followers: Sequence[StageSpec], driver: Driver) -> None:
        self.followers, self.driver = tuple(followers), driver
        self.hashes = {follower.name: param_hash(follower.params) for follower in self.followers}
        self.reports = {name: StageReport(stage=name, param_hash=h) for name, h in self.hashes.items()}
        self.pending: dict[str, list[tuple[StageRecord, str | None]]] = {follower.name: [] for follower in self.followers}
        self.unused: dict[str, set[int]] = {follower.name: set() for follower in self.followers}
        self.claimed: dict[int, tuple[str, ...]] = {}
        self.function = functools.partial(
            run_chain, lead=lead.task, steps=self.followers, digest=inputs_digest, work_dir=card_work_dir
        )

    def tasks(self, leads: list[CardTask]) -> Iterator[ChainTask]:
        """The chains of a claimed batch: each card's state and latest results now, and the
        followers this driver could claim it for (a card another run holds for a follower
        stops before it)."""
        ids = [task.card_id for task in leads]
        if not ids:
            return
        states = dict(db.session.execute(select(Card.id, Card.state).where(Card.id.in_(ids))).all())
        latest: dict[int, dict[str, ResultView]] = {card_id: {} for card_id in ids}
        own: dict[str, dict[int, StageResult]] = {name: {} for name in self.hashes}
        for result in db.session.scalars(select(StageResult).where(StageResult.card_id.in_(ids)).order_by(StageResult.id)):
            latest[result.card_id][result.stage] = ResultView(
                stage=result.stage,
                param_hash=result.param_hash,
                status=result.status,
                outcome=result.outcome,
                metrics={k: v for k, v in (result.metrics or {}).items() if k != "inputs_digest"},
                artifacts=dict(result.artifacts or {}),
            )
            if self.hashes.get(result.stage) == result.param_hash:
                own[result.stage][result.card_id] = result
        finished = {
            card_id: {
                name: str(result.metrics.get("inputs_digest"))
                for name, results in own.items()
                if (result := results.get(card_id)) is not None and result.status in ("done", "skipped")
            }
            for card_id in ids
        }
        seen = {
            name: {card_id: result_fingerprint(r.status, r.started_at) for card_id, r in results.items()}
            for name, results in own.items()
        }
        collection_wide = {card_id: collection_decisions(kinds) for card_id, kinds in approved_annotations(ids).items()}
        db.session.commit()  # no read transaction open while the cards compute
        claimed_by: dict[str, set[int]] = {}
        for name, h in self.hashes.items():
            round_ = self.driver.claim(name, h, ids, {card_id: seen[name].get(card_id) for card_id in ids})
            claimed_by[name] = set(round_.claimed)
        for task in leads:
            stages = tuple(name for name in self.hashes if task.card_id in claimed_by[name])
            self.claimed[task.card_id] = stages
            yield ChainTask(
                lead=task,
                state=str(states.get(task.card_id, "ingested")),
                results=tuple(latest[task.card_id].values()),
                claimed=stages,
                finished=finished[task.card_id],
                approved=collection_wide.get(task.card_id, {}),
            )

    def take(self, item: ChainOutcome | StageRecord) -> StageRecord:
        """The lead's record of a finished chain; the followers' records are kept for
        :meth:`write`. A bare record is a chain that never ran (a worker died, the executor
        failed): its followers made nothing."""
        made = item.records if isinstance(item, ChainOutcome) else ((item, None),)
        lead = made[0][0]
        ran = set()
        for record, digest in made[1:]:
            ran.add(record.stage)
            self.pending[record.stage].append((record, digest))
            report = self.reports[record.stage]
            _count(report, record)
            report.chained += 1
            report.chained_cards.append(record.card_id)
            report.seconds += record.seconds
        for stage in self.claimed.pop(lead.card_id, ()):
            if stage not in ran:
                self.unused[stage].add(lead.card_id)
        return lead

    def write(self) -> None:
        """Write the followers' records in flow order (the lead's are written first) and free
        the follower claims the chains did not use."""
        for name, made in self.pending.items():
            if made:
                digests = {r.card_id: d for r, d in made if d is not None}
                self.reports[name].changed_decisions += write_records([record for record, _ in made], digests, self.driver)
                made.clear()
        unused = {name: ids for name, ids in self.unused.items() if ids}
        if unused:
            session = db.session()
            with one_writer(session):
                connection = session.connection()
                for name, ids in unused.items():
                    connection.execute(self.driver.release_statement(name, ids))
                session.commit()
            for ids in self.unused.values():
                ids.clear()


def run_stages(
    specs: Sequence[StageSpec],
    run: Callable[[StageSpec, Sequence[StageSpec], Mapping[str, set[int]]], StageReport],
    chain: bool = True,
) -> Iterator[StageReport]:
    """Run ``specs`` in order, each through ``run(spec, followers, leave_out)`` (which calls
    :func:`run_stage` with those two), and yield each stage's report as it finishes.

    With ``chain``, a stage with ``chains`` runs as a follower of the stage before it in the run
    (:mod:`runs.chains`), then on its own turn over what the chains did not reach; its report
    counts both."""
    followers_of: dict[str, list[StageSpec]] = {}
    lead: StageSpec | None = None
    for spec in specs:
        if chain and lead is not None and spec.chains:
            followers_of[lead.name].append(spec)
        else:
            lead = spec
            followers_of[spec.name] = []
    chained: dict[str, StageReport] = {}
    for spec in specs:
        leave_out = {stage: set(report.chained_cards) for stage, report in chained.items()}
        report = run(spec, followers_of.get(spec.name, ()), leave_out)
        chained.update(report.followers)
        if spec.name in chained:
            report.absorb(chained[spec.name])
        yield report


def waiting_for_people(chunk: int = PLAN_CHUNK) -> dict[str, list[int]]:
    """Cards that wait for the crowd's judgement, by why: ``orientation`` (the orientation step
    asked, or failed, and no crowd or curator has decided it yet) and ``filter_review`` (the
    filter sent it to review and no judgement has come back). A card whose judgement waits
    for a curator (a dispute) is the curators' work, not counted here; nor a card whose
    orientation step has not run."""
    waiting: dict[str, list[int]] = {"orientation": [], "filter_review": []}
    after = 0
    while True:
        cards = list(
            db.session.scalars(
                select(Card)
                .where(Card.state.in_(("pass", "review")), Card.id > after)
                .order_by(Card.id)
                .limit(chunk)
                .options(selectinload(Card.stage_results))
            )
        )
        if not cards:
            return waiting
        work = people_and_decisions([card.id for card in cards])
        for card in cards:
            own = work.get(card.id, {})
            disputed = own.get("judge") is not None and own["judge"].state == "needs_curator"
            if disputed or _judged_not_stereo(own):
                continue
            step = card.latest_results().get("orientation")
            if step is not None and not is_decided(card_orientation(card, own.get("approved", {}))):
                waiting["orientation"].append(card.id)
            elif card.state == "review" and "judge" not in own.get("approved", {}):
                waiting["filter_review"].append(card.id)
        after = cards[-1].id
        db.session.expunge_all()


def _count(report: StageReport, record: StageRecord) -> None:
    report.processed += 1
    if record.status == "failed":
        report.failed += 1
        report.failures.append({"card_id": record.card_id, "reason": record.reason})
    else:
        report.done += 1
        if record.outcome:
            report.outcomes[record.outcome] = report.outcomes.get(record.outcome, 0) + 1


def _words(decision: Mapping[str, Any]) -> str:
    proposed = decision.get("proposed") or {}
    set_flags = [flag for flag, value in proposed.items() if value]
    return f"{decision.get('decision')} ({', '.join(set_flags) or 'upright, positive, eyes in order'})"


def _decision(outcome: str | None, metrics: Mapping[str, Any]) -> dict[str, Any]:
    return {"decision": outcome, "proposed": metrics.get("proposed")}


def decided_changes(session: Any, records: list[StageRecord]) -> list[dict[str, Any]]:
    """Of new orientation records, those whose decision (``auto`` / ``confirm`` / ``ask`` and the
    proposed flags) differs from the card's latest orientation result before them: what a
    collection's refitted head or an operator's word changed, listed in the run's report."""
    new = {r.card_id: r for r in records if r.stage == "orientation" and r.status == "done"}
    if not new:
        return []
    before: dict[int, dict[str, Any]] = {}
    for row in session.scalars(
        select(StageResult)
        .where(StageResult.stage == "orientation", StageResult.status == "done", StageResult.card_id.in_(new))
        .order_by(StageResult.id)
    ):
        before[row.card_id] = _decision(row.outcome, row.metrics or {})
    return [
        {"card_id": card_id, "before": before[card_id], "after": after}
        for card_id, record in sorted(new.items())
        if card_id in before and (after := _decision(record.outcome, record.metrics)) != before[card_id]
    ]


def write_records(
    records: list[StageRecord], digests: dict[int, str] | None = None, driver: Driver | None = None
) -> list[dict[str, Any]]:
    """Upsert results (one row per card, stage and parameters), update card states and release
    the driver's claims on these cards, in one transaction. Returns the orientation decisions the
    records changed (:func:`decided_changes`).

    An upsert, not read-then-insert: a row another run wrote meanwhile (its claim lapsed and
    was taken over, or it ran before claims existed) is overwritten, never a unique-key error.
    """
    if not records:
        return []
    session = db.session()
    with one_writer(session):
        changes = decided_changes(session, records)
        connection = session.connection()
        insert = (postgresql.insert if connection.dialect.name == "postgresql" else sqlite.insert)(StageResult)
        now = utcnow()
        rows = [
            {
                "card_id": record.card_id,
                "stage": record.stage,
                "param_hash": record.param_hash,
                "status": record.status,
                "outcome": record.outcome,
                "reason": record.reason,
                "metrics": {**record.metrics, "inputs_digest": digests[record.card_id]} if digests else record.metrics,
                "artifacts": record.artifacts,
                "started_at": datetime.fromtimestamp(record.started_at, tz=timezone.utc) if record.started_at else None,
                "seconds": record.seconds,
                "code_version": record.code_version,
                "created_at": now,
            }
            # One row per key and statement (PostgreSQL refuses to upsert a row twice in one
            # command); the latest record of a card wins, as it would row by row. Key order is
            # the lock order, so two writers of the same rows queue instead of deadlocking.
            for _, record in sorted({(r.card_id, r.stage, r.param_hash): r for r in records}.items())
        ]
        updated = {
            column: getattr(insert.excluded, column)
            for column in ("status", "outcome", "reason", "metrics", "artifacts", "started_at", "seconds", "code_version")
        }
        connection.execute(
            insert.values(rows).on_conflict_do_update(index_elements=["card_id", "stage", "param_hash"], set_=updated)
        )
        cards = {card.id: card for card in session.scalars(select(Card).where(Card.id.in_({r.card_id for r in records})))}
        for record in records:
            card = cards.get(record.card_id)
            if card is not None and record.stage == "filter":
                card.state = record.outcome if record.status == "done" and record.outcome else "failed"
        if driver is not None:
            for stage in {record.stage for record in records}:
                connection.execute(driver.release_statement(stage, {r.card_id for r in records if r.stage == stage}))
        session.commit()
    return changes


DOWNSTREAM_OF_CULL = ("orientation", "judge", "crop", "rectify", "disparity", "grade", "review", "views")
DOWNSTREAM_OF_RECTIFY = ("disparity", "grade", "views")


def people_and_decisions(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """:func:`core.hooks.people_work` per card (the crowd's latest aggregates, the curator
    review), plus ``"approved"``: the approved decisions the orientation is resolved from
    (:func:`approved_annotations`)."""
    work = people_work(card_ids)
    for card_id, approved in approved_annotations(card_ids).items():
        work.setdefault(card_id, {})["approved"] = approved
    return work


def _status(
    status: str, reason: str | None = None, outcome: str | None = None, metrics: dict[str, Any] | None = None
) -> dict[str, Any]:
    return {"status": status, "outcome": outcome, "reason": reason, "metrics": metrics or {}}


def _crowd_status(
    stage: str, card: Card, aggregate: Any, latest: dict[str, StageResult], orientation: dict[str, Any] | None = None
) -> dict[str, Any]:
    if aggregate is not None:
        metrics = {"label": aggregate.label, "batch": aggregate.batch_id, "answers": aggregate.answers}
        if aggregate.state == "needs_curator":
            return _status("pending", f"waiting for a curator: {aggregate.reasons}", metrics=metrics)
        who = (
            f"curator decision (batch {aggregate.batch_id})"
            if aggregate.resolved_by
            else f"crowd consensus (batch {aggregate.batch_id})"
        )
        outcome = None
        if stage == "judge":
            outcome = "stereo" if aggregate.label.get("is_stereo", True) else "not_stereo"
        return _status("done", who, outcome, metrics)
    if stage == "judge" and card.state == "pass":
        orientation = orientation or card_orientation(card, {})
        if orientation["decided_by"] == "auto":
            return _status(
                "skipped",
                "not needed: the filter passed the card as a stereo pair and the orientation "
                f"step decided it (confidence {orientation['confidence']})",
            )
        if orientation["decided_by"] in ("curator", "operator", "crowd"):
            # crowd without a judge aggregate: people confirmed the step's proposal in a grid.
            return _status("skipped", f"not needed: {orientation['source']}")
        return _status("pending", f"waiting for {orientation['waiting_for']}" if orientation["waiting_for"] else None)
    rectify = latest.get("rectify")
    if stage == "crop" and rectify is not None and rectify.status != "failed":
        return _status("skipped", f"not needed: rectified from {rectify.metrics.get('box_source', 'the filter split')}")
    return _status("pending")


def _review_status(review: Any, latest: dict[str, StageResult]) -> dict[str, Any]:
    if review is None or review.decision == "pending":
        grade = latest.get("grade")
        if grade is None and "disparity" in latest and latest["disparity"].status == "failed":
            return _status("skipped", f"not run: disparity failed ({latest['disparity'].reason})")
        return _status("pending", "waiting for a curator" if review is not None else None)
    metrics = {"grade": review.grade, "auto_grade": review.auto_grade, "version": review.version}
    if review.decision == "sent_back":
        return _status("pending", f"sent back to the crowd: {review.note}".rstrip(": "), metrics=metrics)
    return _status("done", review.note or None, review.decision, metrics)


def _judged_not_stereo(work: dict[str, Any]) -> bool:
    judge = work.get("approved", {}).get("judge")
    return judge is not None and judge.label.get("is_stereo", True) is False


def card_orientation_field(card: Card, work: dict[str, Any]) -> dict[str, Any]:
    """The ``orientation`` of ``keystone cards --json`` (DESIGN.md): null flags while undecided."""
    return public_orientation(card_orientation(card, work.get("approved", {})))


def card_stage_statuses(
    card: Card, only_stage: str | None = None, work: dict[str, Any] | None = None
) -> dict[str, dict[str, Any]]:
    """The stage status map of ``keystone cards --json``: every stage, ``pending`` if not run.

    ``work`` is the card's entry of :func:`people_work` (crowd aggregates and the review); it is
    loaded here when not given.
    """
    latest = card.latest_results()
    if work is None:
        work = people_and_decisions([card.id]).get(card.id, {})
    statuses: dict[str, dict[str, Any]] = {}
    orientation = card_orientation(card, work.get("approved", {}))
    for stage in STAGES if only_stage is None else (only_stage,):
        result = latest.get(stage)
        if (
            stage == "judge"
            and card.state in ("pass", "review")
            and not is_decided(orientation)
            and "orientation" in latest
            and not _judged_not_stereo(work)
        ):
            # The flow rule: an undecided card waits for people, whatever its filter band.
            status = _crowd_status(stage, card, work.get(stage), latest, orientation)
            statuses[stage] = (
                status
                if status["status"] == "pending"
                else _status("pending", f"waiting for {orientation['waiting_for']}", metrics=status["metrics"])
            )
        elif (
            stage == "rectify"
            and result is None
            and card.state in ("pass", "review")
            and not is_decided(orientation)
            and not _judged_not_stereo(work)
        ):
            statuses[stage] = _status(
                "pending", f"not run: the orientation is undecided, waiting for {orientation['waiting_for']}"
            )
        elif card.state == "culled" and stage in DOWNSTREAM_OF_CULL and result is None:
            filter_reason = latest["filter"].reason if "filter" in latest else "culled"
            statuses[stage] = _status("skipped", f"not needed: the card was culled by the filter ({filter_reason})")
        elif stage in ("judge", "crop"):
            statuses[stage] = _crowd_status(stage, card, work.get(stage), latest, orientation)
        elif stage == "review":
            statuses[stage] = _review_status(work.get("review"), latest)
        elif result is not None:
            statuses[stage] = result.as_status()
        elif stage in DOWNSTREAM_OF_RECTIFY and "rectify" in latest and latest["rectify"].status == "failed":
            statuses[stage] = _status("skipped", f"not run: rectification failed ({latest['rectify'].reason})")
        elif stage == "views" and "grade" in latest and latest["grade"].outcome == "failure":
            statuses[stage] = _status("skipped", "not needed: graded failure")
        else:
            statuses[stage] = _status("pending")
    return statuses


@click.command("run")
@click.option(
    "--stages",
    default="filter,orientation,rectify,disparity,grade",
    show_default=True,
    help="Comma-separated stages to run, in order: filter, orientation, rectify, disparity, grade, "
    "views (views is optional per scene and not in the default).",
)
@click.option(
    "--workers", default=1, show_default=True, type=click.IntRange(1, 256), help="Worker processes (1 runs inline on one core)."
)
@click.option(
    "--executor",
    "executor_kind",
    type=click.Choice(["local", "dask"]),
    default="local",
    show_default=True,
    help="Where per-card work runs: a local process pool or a dask cluster.",
)
@click.option("--scheduler", help="dask scheduler address (with --executor dask); default a local cluster.")
@click.option(
    "--wait/--no-wait",
    "wait_for_held",
    default=True,
    show_default=True,
    help="When the only cards left are held by another run: wait for it to finish them (or for "
    "its claims to lapse, then take them over), or leave them and exit with status 3.",
)
@click.option(
    "--claim-ttl-s",
    type=click.FloatRange(min=1.0),
    default=DEFAULT_CLAIM_TTL_S,
    show_default=True,
    envvar="KEYSTONE_CLAIM_TTL_S",
    help="Seconds a claim on a card outlives this run's last heartbeat (it beats every quarter of "
    "that): how long a killed run keeps others off its cards. Env: KEYSTONE_CLAIM_TTL_S.",
)
@click.option(
    "--claim-batch",
    type=click.IntRange(1, 1000),
    default=DEFAULT_CLAIM_BATCH,
    show_default=True,
    help="Cards claimed per database transaction.",
)
@click.option(
    "--chain/--stage-by-stage",
    "chain",
    default=True,
    show_default=True,
    help="Let a worker take a card on through the stages after one whose inputs are that card's "
    "own results (orientation after the filter; disparity, grade and views after rectify), "
    "decoding each file once, or run every stage over all cards before the next. The results "
    "are the same.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the run report as one JSON document.")
@with_appcontext
def run_command(
    stages: str,
    workers: int,
    executor_kind: str,
    scheduler: str | None,
    wait_for_held: bool,
    claim_ttl_s: float,
    claim_batch: int,
    chain: bool,
    as_json: bool,
) -> None:
    """Run pipeline stages over the catalogue, skipping cards already done with the same parameters.

    Resumable: interrupt it at any time and run it again; only unfinished cards are processed.
    Cards that failed are retried.

    Safe to run twice at once (on one machine or many against one database): each run claims
    a card before computing it, so no card-stage is computed twice. A second run takes the
    cards the first has not claimed; when only claimed cards are left it waits for them by
    default (a killed run's claims lapse after --claim-ttl-s and are taken over), or with
    --no-wait leaves them. The JSON report counts them per stage: held_by_other_run,
    done_by_other_run, still_held, taken_over.

    Exit status: 0 done; 1 if any card failed; 3 if --no-wait left cards another run holds
    (and none failed).
    """
    from core.console import data_dir, emit_json, ensure_database, progress_bar, say
    from runs.leftovers import clear_leftovers

    names = [name.strip() for name in stages.split(",") if name.strip()]
    unknown = [name for name in names if name not in RUNNABLE_STAGES]
    if unknown or not names:
        raise click.BadParameter(
            f"unknown or unavailable stage(s): {', '.join(unknown) or '(none)'}; available: {', '.join(RUNNABLE_STAGES)}",
            param_hint="--stages",
        )
    ensure_database()
    clear_leftovers(as_json)  # what killed runs and exports left behind
    specs = available_stages()
    reports = []
    driver = Driver(db.engine, ttl_s=claim_ttl_s)
    waiting_said: set[tuple[str, int]] = set()

    def say_waiting(stage: str) -> Callable[[int, set[str]], None]:
        def said(count: int, holders: set[str]) -> None:
            if (stage, count) not in waiting_said:
                waiting_said.add((stage, count))
                say(f"{stage}: waiting for {count} card(s) held by another run ({', '.join(sorted(holders))})", True)

        return said

    try:
        with make_executor(executor_kind, workers, scheduler) as executor, driver.running():

            def run_one(spec: StageSpec, followers: Sequence[StageSpec], leave_out: Mapping[str, set[int]]) -> StageReport:
                with progress_bar(spec.name, enabled=not as_json) as progress:
                    return run_stage(
                        spec,
                        data_dir=data_dir(),
                        executor=executor,
                        on_start=progress.start,
                        on_record=progress.advance,
                        driver=driver,
                        wait_for_held=wait_for_held,
                        claim_batch=claim_batch,
                        on_wait=say_waiting(spec.name),
                        followers=followers,
                        leave_out=leave_out,
                    )

            for report in run_stages([specs[name] for name in names], run_one, chain):
                name = report.stage
                reports.append(report)
                if not as_json:
                    outcomes = ", ".join(f"{k} {v}" for k, v in sorted(report.outcomes.items())) or "-"
                    elsewhere = (
                        f"; done by another run {report.done_by_other_run}"
                        if report.held_by_other_run or report.done_by_other_run
                        else ""
                    )
                    say(
                        f"{name}: processed {report.processed} in {report.seconds:.1f} s "
                        f"(already done {report.skipped_existing}{elsewhere}; outcomes: {outcomes}; "
                        f"failed {report.failed})",
                        as_json,
                    )
                    for failure in report.failures:
                        say(f"  card {failure['card_id']}: {failure['reason']}", as_json)
                    for change in report.changed_decisions:
                        say(
                            f"  card {change['card_id']}: decision changed {_words(change['before'])} -> {_words(change['after'])}",
                            as_json,
                        )
                if report.still_held:
                    say(
                        f"{name}: left {report.still_held} card(s) that another run holds "
                        f"({', '.join(sorted(report.held_by))}); rerun when it is done, or without --no-wait "
                        "to wait for it",
                        True,
                    )
    except RuntimeError as exc:
        raise click.ClickException(str(exc)) from exc
    waiting = waiting_for_people()
    counts = {reason: len(ids) for reason, ids in waiting.items()}
    if sum(counts.values()):
        say(
            f"waiting for people: {counts['orientation']} card(s) whose orientation the step could not decide, "
            f"{counts['filter_review']} the filter sent to review (`keystone crowd create-batch --from-review` "
            "makes a judge batch of them)",
            as_json,
        )
    if as_json:
        emit_json(
            {
                "stages": [report.as_json() for report in reports],
                "waiting_for_people": counts,
                "workers": workers,
                "executor": executor_kind,
                "driver": driver.id,
                "claim_ttl_s": driver.ttl_s,
                "heartbeats": driver.heartbeats,
            }
        )
    if any(report.failed for report in reports):
        raise SystemExit(1)
    if any(report.still_held for report in reports):
        raise SystemExit(EXIT_HELD)


CARDS_CHUNK = 1000  # cards read, described and written per step of `keystone cards`


def card_rows(
    stage: str | None = None, state: str | None = None, collection_name: str | None = None, chunk: int = CARDS_CHUNK
) -> Iterator[dict[str, Any]]:
    """The rows of ``keystone cards``, in id order, read a chunk at a time (keyset paging on the
    id, each chunk's results and people's work loaded together), so memory does not grow with
    the catalogue. Call inside :func:`core.db.read_only`."""
    from core.models import Collection

    after = 0
    while True:
        query = select(Card).where(Card.id > after).order_by(Card.id).limit(chunk).options(selectinload(Card.stage_results))
        if state:
            query = query.where(Card.state == state)
        if collection_name:
            query = query.join(Collection).where(Collection.name == collection_name)
        cards = list(db.session.scalars(query))
        if not cards:
            return
        work = people_and_decisions([card.id for card in cards])
        for card in cards:
            yield {
                "id": card.id,
                "source": card.source_name,
                "accession": card.accession,
                "state": card.state,
                "orientation": card_orientation_field(card, work.get(card.id, {})),
                "stages": card_stage_statuses(card, stage, work.get(card.id, {})),
            }
        after = cards[-1].id
        db.session.expunge_all()  # this chunk's cards and results are written out: let them go


@click.command("cards")
@click.option("--stage", type=click.Choice(list(STAGES)), help="Show only this stage's status.")
@click.option("--state", type=click.Choice(list(CARD_STATES)), help="Only cards in this state.")
@click.option("--collection", "collection_name", help="Only cards of this collection.")
@click.option("--json", "as_json", is_flag=True, help="Print the cards as one JSON document.")
@with_appcontext
def cards_command(stage: str | None, state: str | None, collection_name: str | None, as_json: bool) -> None:
    """List cards with their stage statuses (streamed: any catalogue size in constant memory)."""
    import sys

    from core.console import ensure_database
    from core.db import read_only

    ensure_database()
    count = 0
    with read_only():
        rows = card_rows(stage, state, collection_name)
        if as_json:
            # One JSON document, written a card at a time.
            out = sys.stdout
            out.write('{"cards": [')
            for row in rows:
                out.write(("\n  " if count == 0 else ",\n  ") + json.dumps(row, default=str))
                count += 1
            out.write("\n]}\n" if count else "]}\n")
            out.flush()
            return
        for row in rows:
            summary = "  ".join(
                f"{name}={info['outcome'] or info['status']}"
                for name, info in row["stages"].items()
                if info["status"] != "pending"
            )
            click.echo(f"{row['id']:>6}  {row['state']:<8}  {row['source']:<48}  {summary}")
            count += 1
    click.echo(f"{count} card(s)")
