"""Chained stages: a worker takes one card through consecutive stages in one go.

``keystone run`` goes stage by stage: every card through the filter, then every card through
the orientation step, and so on, with the driver writing each stage's results before the next
stage is planned from them. Each stage then decodes what it reads from disk afresh: a ~3000 px
JPEG scan costs ~34 ms to decode even at half size, and a rectified view ~12 ms, so a card's
filter and orientation step decode its scan twice, and the disparity, grade and views stages
read back the views the rectify stage has just written.

A stage whose inputs come from the card's own stage results alone (no people's decisions:
:attr:`pipeline.stages.spec.StageSpec.chains`) can run in the same worker right after the stage
before it, on the same card, inside :func:`pipeline.io.shared_decodes`: a second read of a file
gets the first one's decode. The worker computes the follower's inputs with the same builder the
driver plans with (the stage module's, over :class:`pipeline.results.CardResults`), from a
snapshot of the card's results the driver sends along and the records the chain has just made, so
the records are those a stage-by-stage run writes. Everything here is what a pool or dask worker
runs, so it lives in ``pipeline/`` and loads no web or database layer (``runs.loop`` is the
driver's side).
The driver still writes every record, claims every card for every stage it computes, and runs
each follower stage by stage afterwards for whatever a chain did not reach (a card another run
holds, a follower already done with the same inputs, a chain cut short by a failure).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .io import shared_decodes
from .records import CardTask, StageRecord, card_work_dir, inputs_digest, param_hash
from .results import FINISHED, ResultView, StageResultLike
from .runner import clear_stale_temp_files
from .stages.spec import StageSpec

__all__ = ["ChainCard", "ChainOutcome", "ChainTask", "run_chain"]


@dataclass
class ChainCard:
    """The card as the input builders see it (:class:`pipeline.results.CardResults`): its state
    and its latest result per stage. Starts from the driver's snapshot; each record the chain
    makes becomes that stage's latest, and a filter record sets the state as the driver will when
    it writes it."""

    id: int
    state: str
    results: dict[str, StageResultLike] = field(default_factory=dict)

    def latest_results(self) -> dict[str, StageResultLike]:
        return dict(self.results)

    def record(self, record: StageRecord) -> None:
        self.results[record.stage] = record
        if record.stage == "filter":  # runs.writes.write_records
            self.state = record.outcome if record.status == "done" and record.outcome else "failed"


@dataclass(frozen=True)
class ChainTask:
    """One card's chain: the lead stage's task, the card's state and latest results when the
    driver claimed it, and the follower stages (in order) this driver holds the card for."""

    lead: CardTask
    state: str
    results: tuple[ResultView, ...]
    claimed: tuple[str, ...]
    # follower stage -> inputs digest of its finished result with these parameters (when there
    # is one): the chain stops there, as the stage would find it already done
    finished: Mapping[str, str] = field(default_factory=dict)
    # people's decisions the followers' inputs read, as the plain values each follower declares
    # (StageSpec.plain_decisions: the orientation step's learned head in force and operator's
    # word), looked up by the driver: a worker has no database
    approved: Mapping[str, Any] = field(default_factory=dict)

    @property
    def card_id(self) -> int:  # what pipeline.runner.run_tasks reads of a task
        return self.lead.card_id

    @property
    def work_dir(self) -> str:
        return self.lead.work_dir


@dataclass(frozen=True)
class ChainOutcome:
    """The records one chain made, lead first, each with the digest of the inputs it ran on
    (None for the lead: the driver knows its inputs)."""

    records: tuple[tuple[StageRecord, str | None], ...]


def run_chain(chain: ChainTask, lead: Callable[[CardTask], StageRecord], steps: Sequence[StageSpec]) -> ChainOutcome:
    """Run ``lead`` on the card, then each stage of ``steps`` while the card qualifies for it (as
    ``runs.planning.pending_cards`` would plan it), all inside one
    :func:`pipeline.io.shared_decodes` block. Runs in a worker; returns plain records."""
    with shared_decodes():
        first = lead(chain.lead)
        made: list[tuple[StageRecord, str | None]] = [(first, None)]
        card = ChainCard(chain.card_id, chain.state, {result.stage: result for result in chain.results})
        card.record(first)
        for step in steps:
            if made[-1][0].status not in FINISHED or step.name not in chain.claimed:
                break  # the stage before failed, or another run holds the card for this one
            if card.state not in step.eligible_states:
                break
            required = card.results.get(step.requires) if step.requires else None
            if step.requires and (required is None or required.status not in FINISHED):
                break
            inputs = dict(step.inputs(card, dict(chain.approved))) if step.inputs is not None else {}
            if step.ready is not None and not step.ready(card, inputs):
                break
            digest = inputs_digest(inputs)
            if chain.finished.get(step.name) == digest:
                break  # already done with these inputs: the stage's own pass counts it
            task = CardTask(
                card_id=chain.card_id,
                content_hash=chain.lead.content_hash,
                image_path=chain.lead.image_path,
                work_dir=str(
                    card_work_dir(Path(chain.lead.data_dir), chain.lead.content_hash, step.name, param_hash(step.params))
                ),
                data_dir=chain.lead.data_dir,
                inputs=inputs,
            )
            clear_stale_temp_files(task)
            record = step.task(task)
            made.append((record, digest))
            card.record(record)
    return ChainOutcome(records=tuple(made))
