"""`keystone run`, `keystone worker` and `keystone cards`."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any, TypeVar

import click
from flask.cli import with_appcontext
from sqlalchemy import select
from sqlalchemy.orm import selectinload

from core.db import db
from core.models import CARD_STATES, Card
from pipeline.decided_orientation import public_orientation
from pipeline.stages.spec import StageSpec, declared_stages, flow_stages
from runs.card_state import card_states, waiting_for_people
from runs.claims import DEFAULT_CLAIM_BATCH, DEFAULT_CLAIM_TTL_S, Driver
from runs.executors import make_executor
from runs.loop import EXIT_HELD, run_stage, run_stages
from runs.report import StageReport
from runs.specs import available_stages, default_run_stages, runnable_stages
from runs.worker import DEFAULT_FULL_EVERY_S, DEFAULT_POLL_S
from runs.writes import decision_words


def _stages_help() -> str:
    """The ``--stages`` help, from the stage modules' declarations."""
    declared = declared_stages()
    on_request = [name for name, declaration in declared.items() if declaration.keystone_run == "on_request"]
    optional = f" ({', '.join(on_request)}: only when named, not in the default)" if on_request else ""
    return f"Comma-separated stages to run, in order: {', '.join(runnable_stages())}{optional}."


def _chain_help() -> str:
    """The ``--chain`` help, naming the stages whose declarations say they chain."""
    chaining = [name for name, declaration in declared_stages().items() if declaration.chains]
    return (
        "Let a worker take a card on through the stages after one whose inputs are that card's "
        f"own results ({', '.join(chaining)}: each right after the stage before it in the run), "
        "decoding each file once, or run every stage over all cards before the next. The results "
        "are the same."
    )


F = TypeVar("F", bound=Callable[..., Any])


def where_it_runs(command: F) -> F:
    """The options ``keystone run`` and ``keystone worker`` share: which stages, and on what."""
    options = (
        click.option("--stages", default=",".join(default_run_stages()), show_default=True, help=_stages_help()),
        click.option(
            "--workers",
            default=1,
            show_default=True,
            type=click.IntRange(1, 256),
            help="Worker processes (1 runs inline on one core).",
        ),
        click.option(
            "--executor",
            "executor_kind",
            type=click.Choice(["local", "dask"]),
            default="local",
            show_default=True,
            help="Where per-card work runs: a local process pool or a dask cluster.",
        ),
        click.option("--scheduler", help="dask scheduler address (with --executor dask); default a local cluster."),
    )
    for option in reversed(options):
        command = option(command)
    return command


def chosen_stages(stages: str) -> list[str]:
    """The ``--stages`` names, checked against the stages that can run."""
    names = [name.strip() for name in stages.split(",") if name.strip()]
    runnable = runnable_stages()
    unknown = [name for name in names if name not in runnable]
    if unknown or not names:
        raise click.BadParameter(
            f"unknown or unavailable stage(s): {', '.join(unknown) or '(none)'}; available: {', '.join(runnable)}",
            param_hint="--stages",
        )
    return names


@click.command("run")
@where_it_runs
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
    help=_chain_help(),
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

    names = chosen_stages(stages)
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
                            f"  card {change['card_id']}: decision changed {decision_words(change['before'])} -> {decision_words(change['after'])}",
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

    specs = available_stages()  # the stage catalogue once: staleness builds each stage's inputs
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
        states = card_states(cards, stage, specs=specs)
        for card in cards:
            state_now = states[card.id]
            yield {
                "id": card.id,
                "source": card.source_name,
                "accession": card.accession,
                "state": card.state,
                "orientation": public_orientation(state_now.orientation),
                "stages": state_now.statuses,
            }
        after = cards[-1].id
        db.session.expunge_all()  # this chunk's cards and results are written out: let them go


@click.command("cards")
@click.option("--stage", type=click.Choice(list(flow_stages())), help="Show only this stage's status.")
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


@click.command("worker")
@click.option("--once", is_flag=True, help="Run one round over the catalogue, then exit (0 done, 1 if any card failed).")
@where_it_runs
@click.option(
    "--poll-s",
    type=click.FloatRange(min=0.1),
    default=DEFAULT_POLL_S,
    show_default=True,
    help="Seconds between looks for new decisions (one small query each).",
)
@click.option(
    "--full-every-s",
    type=click.FloatRange(min=1.0),
    default=DEFAULT_FULL_EVERY_S,
    show_default=True,
    help="Run a round at least this often even when nothing was decided (new failures' retries).",
)
@click.option(
    "--parent-pid", type=click.IntRange(min=1), hidden=True, help="Exit when this process is gone (set by keystone serve)."
)
@click.option("--json", "as_json", is_flag=True, help="Print each round as one JSON line.")
@with_appcontext
def worker_command(
    once: bool,
    stages: str,
    workers: int,
    executor_kind: str,
    scheduler: str | None,
    poll_s: float,
    full_every_s: float,
    parent_pid: int | None,
    as_json: bool,
) -> None:
    """Recompute pending and stale work as people's decisions arrive, until stopped.

    The loop's other half: a curator's new eye order, a settled dispute or the crowd's boxes
    make a card's results stale or its next stage due, and the worker recomputes it (a new grade
    returns the card to the review queue). It runs a round at start, whenever people decide
    something, and every --full-every-s. Safe beside `keystone run` and other workers: it
    computes through the same claims and leaves cards another run holds. `keystone serve` starts
    one unless --no-worker. Ctrl+C or SIGTERM stops it and frees its claims.
    """
    import signal

    from core.console import data_dir, ensure_database, say
    from runs.leftovers import clear_leftovers
    from runs.worker import BackgroundWorker, WorkerRound

    names = chosen_stages(stages)
    ensure_database()
    clear_leftovers(True)

    def said(done: WorkerRound) -> None:
        if as_json:
            click.echo(json.dumps(done.as_json(), default=str))
            return
        parts = (
            ", ".join(f"{stage['stage']} {stage['processed']}" for stage in done.stages if stage["processed"]) or "nothing to do"
        )
        say(f"worker round ({done.trigger}): {parts} in {done.seconds:.1f} s; failed {done.failed}", False)

    def stop(signum: int, frame: Any) -> None:
        raise SystemExit(0)  # unwinds through the claims and the worker row, which free themselves

    signal.signal(signal.SIGTERM, stop)
    driver = Driver(db.engine)
    try:
        with make_executor(executor_kind, workers, scheduler) as executor, driver.running():
            worker = BackgroundWorker(
                names,
                executor,
                driver,
                data_dir(),
                poll_s=poll_s,
                full_every_s=full_every_s,
                parent_pid=parent_pid,
                on_round=said,
            )
            if not as_json and not once:
                say(f"keystone worker {driver.id}: watching for decisions every {poll_s:g} s (Ctrl+C to stop)", False)
            rounds = worker.run(once=once)
    except RuntimeError as exc:
        raise click.ClickException(str(exc)) from exc
    except KeyboardInterrupt:
        return
    if once and any(done.failed for done in rounds):
        raise SystemExit(1)
