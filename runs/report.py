"""The report of one stage's run: what was computed, skipped, failed, held and chained."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pipeline.records import StageRecord
from pipeline.runner import InFlight


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
    # before it (pipeline.chains); and the reports of the stages chained after this one.
    chained: int = 0
    chained_cards: list[int] = field(default_factory=list)
    followers: dict[str, StageReport] = field(default_factory=dict)
    # The orientation step's decisions this run changed on cards it had decided before (a
    # collection's refitted head, an operator's word): card, before, after (decided_changes).
    changed_decisions: list[dict[str, Any]] = field(default_factory=list)
    # The in-flight window the executor's threads gave (pipeline.runner.in_flight_window; 0
    # inline), the most cards this stage had in flight at once, and when it sent them.
    flight: InFlight = field(default_factory=InFlight)

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
            "window": self.flight.window,
            "most_in_flight": self.flight.most,
            "seconds": round(self.seconds, 3),
            "cards_per_second": round(self.processed / self.seconds, 3) if self.seconds > 0 else None,
        }


def count_record(report: StageReport, record: StageRecord) -> None:
    report.processed += 1
    if record.status == "failed":
        report.failed += 1
        report.failures.append({"card_id": record.card_id, "reason": record.reason})
    else:
        report.done += 1
        if record.outcome:
            report.outcomes[record.outcome] = report.outcomes.get(record.outcome, 0) + 1
