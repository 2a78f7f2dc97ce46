"""The run loop: claim cards in batches, send them through an executor (chained stages
along with their lead), write what comes back in batches."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

from sqlalchemy import select

from core.db import db, one_writer
from core.hooks import after_write, approved_decisions
from core.models import Card, StageResult
from pipeline.chains import ChainOutcome, ChainTask, run_chain
from pipeline.records import CardTask, StageRecord, card_work_dir, inputs_digest, param_hash
from pipeline.results import ResultView
from pipeline.runner import run_tasks
from pipeline.stages.spec import StageSpec
from runs.claims import DEFAULT_CLAIM_BATCH, Driver, result_fingerprint
from runs.executors import dispatch_window
from runs.planning import PlannedCard, pending_cards
from runs.report import StageReport, count_record
from runs.writes import write_records

WRITE_BATCH = 50
WRITE_INTERVAL_S = 2.0
# How often a run waiting for cards another run holds looks again (at most; a quarter of the
# claim lifetime when that is shorter).
WAIT_POLL_S = 2.0
# `keystone run` exit status when --no-wait left cards that another run holds.
EXIT_HELD = 3


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
    this one where the card qualifies (:mod:`pipeline.chains`); their records are written here and
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
    planned = {card.card_id: card for card in cards if card.card_id not in skip}
    del cards
    digests = {card_id: inputs_digest(card.inputs) for card_id, card in planned.items() if spec.inputs is not None}
    db.session.commit()  # release the read transaction while workers compute
    if on_start is not None:
        on_start(len(planned))
    root = str(data_dir)

    def card_task(card: PlannedCard) -> CardTask:
        # A card's work order is made when it is claimed, not at planning: a 250,000-card run
        # holds its planned rows, not three paths for every card besides.
        return CardTask(
            card_id=card.card_id,
            content_hash=card.content_hash,
            image_path=str(data_dir / card.stored_path),
            work_dir=str(card_work_dir(data_dir, card.content_hash, spec.name, phash)),
            data_dir=root,
            inputs=card.inputs,
        )

    clock = time.perf_counter()
    computed: list[int] = []
    held: dict[int, str] = {}
    chain = _Chain(spec, followers, driver) if followers else None
    if chain is not None:
        report.followers = chain.reports
    function: Callable[[Any], Any] = spec.task if chain is None else chain.function
    # As many cards in flight as the executor has threads to compute them, times a small
    # multiple (pipeline.runner.WINDOW_PER_THREAD); a dask cluster's is re-read as workers join.
    window = dispatch_window(executor)

    def claimed_tasks(card_ids: list[int]) -> Iterator[CardTask | ChainTask]:
        # Claimed a batch at a time, just before the executor wants them, so a second run
        # finds the cards this one has not reached yet.
        for start in range(0, len(card_ids), claim_batch):
            batch_ids = card_ids[start : start + claim_batch]
            claim = driver.claim(spec.name, phash, batch_ids, {card_id: planned[card_id].fingerprint for card_id in batch_ids})
            report.taken_over += len(claim.taken_over)
            report.done_by_other_run += len(claim.finished_elsewhere)
            for card_id in batch_ids:
                held.pop(card_id, None)
            held.update(claim.held)
            if chain is None:
                for card_id in claim.claimed:
                    yield card_task(planned[card_id])
            else:
                yield from chain.tasks([card_task(planned[card_id]) for card_id in claim.claimed])

    def compute(card_ids: list[int]) -> None:
        batch: list[StageRecord] = []
        last_write = time.monotonic()
        for item in run_tasks(
            function, claimed_tasks(card_ids), executor, stage=spec.name, param_hash=phash, window=window, flight=report.flight
        ):
            record = item if chain is None else chain.take(item)
            batch.append(record)
            computed.append(record.card_id)
            count_record(report, record)
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

    compute(list(planned))
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
    """The driver's side of chained stages (:mod:`pipeline.chains`) for one lead stage: claims the
    followers with the lead, sends each card's snapshot along, writes what the chains made
    after the lead's records of the same batch, and frees the claims a chain did not use."""

    def __init__(self, lead: StageSpec, followers: Sequence[StageSpec], driver: Driver) -> None:
        self.followers, self.driver = tuple(followers), driver
        self.hashes = {follower.name: param_hash(follower.params) for follower in self.followers}
        self.reports = {name: StageReport(stage=name, param_hash=h) for name, h in self.hashes.items()}
        self.pending: dict[str, list[tuple[StageRecord, str | None]]] = {follower.name: [] for follower in self.followers}
        self.unused: dict[str, set[int]] = {follower.name: set() for follower in self.followers}
        self.claimed: dict[int, tuple[str, ...]] = {}
        self.function = functools.partial(run_chain, lead=lead.task, steps=self.followers)

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
                reason=result.reason,
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
        # The people's decisions the followers' builders read, as the plain values each declares.
        plain = [follower.plain_decisions for follower in self.followers if follower.plain_decisions is not None]
        decided = approved_decisions(ids) if plain else {}
        collection_wide = {
            card_id: {key: value for decisions in plain for key, value in decisions(kinds).items()}
            for card_id, kinds in decided.items()
        }
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
            count_record(report, record)
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
    (:mod:`pipeline.chains`), then on its own turn over what the chains did not reach; its report
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
