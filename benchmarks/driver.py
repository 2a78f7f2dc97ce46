"""``keystone bench driver``: the run driver alone, over a stage that computes nothing.

Fills a throwaway SQLite catalogue (in a temporary folder, whatever database is configured) with
N ingested cards by bulk insert, then runs one stage over them through the driver's own code:
:func:`runs.loop.run_stage` plans it (:func:`runs.planning.pending_cards`), claims the cards in
batches (:class:`runs.claims.Driver`), sends them through the executor's in-flight window
(:func:`pipeline.runner.run_tasks`, sized by :func:`runs.executors.dispatch_window`) and writes
the records in batches (:func:`runs.writes.write_records`). The stage is the filter's spec
(its eligible cards, its planning in one query, its write of the card's state) with the task
swapped for :func:`noop_task`, which returns a record without reading an image: what is left
is the driver's cost per card, the number a cluster's card rate must stay under.

Per catalogue size (25,000 and 250,000 by default):

- ``planned_per_second``: cards over the seconds from the call to the first card sent
  (planning, the tasks built, the read transaction closed);
- ``dispatched_per_second``: cards sent to the executor over the seconds from the end of
  planning to the last one sent;
- ``written_per_second``: cards over the seconds from the end of planning to the run's end
  (every record written and its claim released);
- ``most_in_flight`` and ``window``: the most cards the driver had in flight at once, and the
  window the executor's threads gave;
- ``driver_cpu_ms_per_card``: CPU of this process (user + system, all its threads: with
  ``--executor dask`` and no ``--scheduler`` that includes the local cluster's scheduler, which
  runs here) over the run, per card: ``1000 / driver_cpu_ms_per_card`` is the card rate one core of driver sustains;
- ``peak_rss_mb``: this process's peak resident memory during the run (``VmHWM`` of
  /proc/self/status, reset through /proc/self/clear_refs just before the run; ``ru_maxrss``,
  the whole process's high-water mark, where that is not possible: ``memory_measure`` says
  which), beside ``rss_before_mb``; the workers' memory is not counted.

The executor is started and warmed (every worker has run a task) before the clock starts.
"""

from __future__ import annotations

import json
import resource
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from pipeline.records import CardTask, StageRecord

DEFAULT_CARDS = (25_000, 250_000)
FILL_CHUNK = 5000
COLLECTION = "bench-driver"


@dataclass(frozen=True)
class NoOpParams:
    """The no-op stage's parameters: its own parameter hash, so no real filter result counts."""

    bench: str = "driver"


def noop_task(task: CardTask, *, param_hash: str) -> StageRecord:
    """A filter record that passes the card, with the size of metrics a real one has, computed
    from nothing (no image read)."""
    return StageRecord(
        card_id=task.card_id,
        stage="filter",
        param_hash=param_hash,
        status="done",
        outcome="pass",
        metrics={"good_match_fraction": 0.25, "matches": 400, "left_box": [20, 30, 690, 670], "right_box": [710, 30, 1380, 670]},
        started_at=time.time(),
        seconds=0.0,
        code_version="bench",
    )


def fill_catalogue(count: int) -> float:
    """Bulk-insert ``count`` ingested cards in one collection; seconds taken."""
    import hashlib

    from sqlalchemy import insert

    from core.db import db
    from core.models import Card, Collection

    clock = time.perf_counter()
    collection = Collection(name=COLLECTION)
    db.session.add(collection)
    db.session.flush()
    for start in range(0, count, FILL_CHUNK):
        rows = [
            {
                "collection_id": collection.id,
                "content_hash": hashlib.sha256(f"bench-driver-{number}".encode()).hexdigest(),
                "stored_path": f"originals/bench/{number:07d}.jpg",
                "source_name": f"bench-{number:07d}.jpg",
                "source_path": "(synthetic)",
                "accession": f"2026.0003.{number:06d}",
                "width": 1400,
                "height": 700,
                "image_format": "JPEG",
                "byte_size": 350_000,
                "state": "ingested",
                "source_metadata": {"title": f"Synthetic card {number}", "date": "1898", "creator": "Keystone View Co."},
            }
            for number in range(start, min(count, start + FILL_CHUNK))
        ]
        db.session.execute(insert(Card), rows)
    db.session.commit()
    return time.perf_counter() - clock


def _rss_mb(field_name: str) -> float | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field_name + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def reset_peak_memory() -> str:
    """Start a fresh high-water mark of this process's resident memory; says which measure
    :func:`peak_memory_mb` will give."""
    try:
        Path("/proc/self/clear_refs").write_text("5")  # Linux 4.0+: VmHWM := VmRSS
    except OSError:
        return "ru_maxrss (the whole process's peak, since it started)"
    return "VmHWM (this process's peak resident memory, reset before each run)"


def peak_memory_mb(measure: str) -> float:
    if measure.startswith("VmHWM"):
        peak = _rss_mb("VmHWM")
        if peak is not None:
            return peak
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _warm(executor: Any, threads: int) -> None:
    """Every worker started and holding this module before the clock starts."""
    if executor is None:
        return
    probe = CardTask(card_id=0, content_hash="0" * 64, image_path="", work_dir="", data_dir="")
    futures = [executor.submit(noop_task, probe, param_hash="warm") for _ in range(4 * max(1, threads))]
    for future in futures:
        future.result(timeout=300)


def measure_driver(count: int, executor: Any, echo: Callable[[str], None]) -> dict[str, Any]:
    """Fill a fresh catalogue of ``count`` cards and run the no-op stage over it through
    ``executor``; the figures of one catalogue size."""
    import dataclasses
    import functools

    from app import create_app
    from core.console import ensure_database
    from core.db import db
    from pipeline.records import param_hash
    from runs.executors import worker_threads
    from runs.loop import run_stage
    from runs.specs import available_stages

    with tempfile.TemporaryDirectory(prefix="keystone-bench-driver-") as folder:
        app = create_app(
            {"SQLALCHEMY_DATABASE_URI": f"sqlite:///{folder}/catalogue.sqlite3", "KEYSTONE_DATA_DIR": f"{folder}/data"},
            instance_path=f"{folder}/instance",
        )
        with app.app_context():
            ensure_database()
            echo(f"filling a catalogue of {count} cards")
            fill_seconds = fill_catalogue(count)
            params = NoOpParams()
            spec = dataclasses.replace(
                available_stages()["filter"],
                params=params,
                task=functools.partial(noop_task, param_hash=param_hash(params)),
            )
            marks: dict[str, float] = {}
            written = 0

            def started(_total: int) -> None:
                marks["planned"] = time.perf_counter()

            def recorded(_record: StageRecord) -> None:
                nonlocal written
                written += 1

            echo(f"running the no-op stage over {count} cards")
            measure = reset_peak_memory()
            rss_before = _rss_mb("VmRSS") or 0.0
            cpu = time.process_time()
            clock = time.perf_counter()
            report = run_stage(spec, data_dir=Path(folder) / "data", executor=executor, on_start=started, on_record=recorded)
            end = time.perf_counter()
            cpu = time.process_time() - cpu
            peak = peak_memory_mb(measure)
            db.session.remove()
            db.engine.dispose()
    planned = marks.get("planned", end)
    flight = report.flight
    # Inline there is no dispatch: a card is "sent" when the loop reaches it.
    sent_by = flight.last_submit if flight.submitted else end
    return {
        "cards": count,
        "processed": report.processed,
        "failed": report.failed,
        "fill_seconds": round(fill_seconds, 2),
        "plan_seconds": round(planned - clock, 3),
        "seconds": round(end - clock, 3),
        "planned_per_second": round(count / max(planned - clock, 1e-9), 1),
        "dispatched_per_second": round((flight.submitted or count) / max(sent_by - planned, 1e-9), 1),
        "written_per_second": round(written / max(end - planned, 1e-9), 1),
        "worker_threads": worker_threads(executor),
        "window": flight.window,
        "most_in_flight": flight.most,
        "driver_cpu_seconds": round(cpu, 2),
        "driver_cpu_ms_per_card": round(1000 * cpu / max(count, 1), 3),
        "rss_before_mb": round(rss_before, 1),
        "peak_rss_mb": round(peak, 1),
        "memory_measure": measure,
    }


def benchmark_driver(
    counts: Sequence[int],
    executor_kind: str,
    workers: int,
    scheduler: str | None = None,
    echo: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """Each catalogue size in turn on one started executor; one JSON-able document."""
    from runs.executors import make_executor, worker_threads

    runs = []
    clock = time.perf_counter()
    with make_executor(executor_kind, workers, scheduler) as executor:
        start_seconds = time.perf_counter() - clock
        threads = worker_threads(executor)
        echo(f"{executor_kind} executor, {threads} worker thread(s), started in {start_seconds:.1f} s")
        _warm(executor, threads)
        for count in counts:
            runs.append(measure_driver(count, executor, echo))
    return {
        "executor": executor_kind,
        "workers": workers if scheduler is None or executor_kind != "dask" else threads,
        "scheduler": "in this process" if executor_kind == "dask" and scheduler is None else scheduler,
        "executor_start_seconds": round(start_seconds, 2),
        "database": "sqlite",
        "runs": runs,
    }


@click.command("driver")
@click.option(
    "--cards",
    "counts",
    multiple=True,
    type=click.IntRange(1, 5_000_000),
    help="Cards in the throwaway catalogue; repeat for several sizes (default 25,000 and 250,000).",
)
@click.option(
    "--executor",
    "executor_kind",
    type=click.Choice(["local", "dask"]),
    default="local",
    show_default=True,
    help="A local process pool or a local dask cluster (single-threaded worker processes).",
)
@click.option("--workers", default=2, show_default=True, type=click.IntRange(1, 256), help="Worker processes (1: inline).")
@click.option(
    "--scheduler",
    help="With --executor dask: a running scheduler's address (its workers, not --workers, compute), so "
    "the scheduler's CPU is not counted as the driver's.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_driver_command(counts: tuple[int, ...], executor_kind: str, workers: int, scheduler: str | None, as_json: bool) -> None:
    """Cards per second the run driver plans, dispatches and writes over a stage that computes
    nothing, the most cards in flight and peak memory, on a throwaway SQLite catalogue."""
    document = benchmark_driver(
        counts or DEFAULT_CARDS, executor_kind, workers, scheduler, echo=lambda m: click.echo(m, err=True)
    )
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return
    click.echo(
        f"{document['executor']} executor, {document['workers']} worker(s) (started in {document['executor_start_seconds']} s)"
    )
    for run in document["runs"]:
        click.echo(
            f"  {run['cards']:>9,} cards: planned {run['planned_per_second']:,.0f}/s, dispatched "
            f"{run['dispatched_per_second']:,.0f}/s, written {run['written_per_second']:,.0f}/s; in flight at most "
            f"{run['most_in_flight']} (window {run['window']}); driver CPU {run['driver_cpu_ms_per_card']} ms a card; "
            f"peak {run['peak_rss_mb']} MB (before {run['rss_before_mb']} MB)"
        )
