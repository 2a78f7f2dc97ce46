"""``keystone bench crowd``: simulated annotators against the served app over HTTP (SQLite or PostgreSQL).

Wire with ``bench_group.add_command(bench_crowd_command)`` (the command is named "crowd").

What runs: a throwaway instance (a SQLite file, or an empty database named by URL; a data dir) with generated cards ingested the normal
way, one batch and invited workers; the app is served by :func:`app.serving.serve` (waitress, or
gunicorn's workers) in a *child process* (so the server does not share a GIL with the 50 client
threads, as in production); annotators arrive over ``ramp_s`` seconds; each simulated
annotator is a thread with one keep-alive ``http.client`` connection that opens its invite page,
then fetches and submits through the JSON API with the signed ``X-Crowd-Token`` header, thinking
for a random while between seeing a task and answering it. Every tenth submit is posted twice
(a retried POST): it must return the stored answer, not a new one.

What is checked afterwards, in the database: every acknowledged answer is stored (``lost``),
nothing is stored that was not acknowledged (``unacknowledged``), no (item, worker) pair twice
and no item beyond N answers (``duplicates``, ``over_capacity_items``), no 5xx.
Latencies are wall-clock milliseconds per request as the client sees them (loopback).
"""

from __future__ import annotations

import http.client
import json
import math
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import click
import numpy as np

TARGET_P95_MS = 100.0
DEFAULT_RAMP_S = 2.0  # annotators arrive over two seconds, then all work at once
REPLAY_EVERY = 10  # every tenth submit is posted twice, as a retried POST would be
ALL_RESERVED_RETRIES = 200  # bounded wait when every open slot is held by someone else
_WORKER_TOKEN = re.compile(r'data-worker-token="([^"]*)"')


# ---------------------------------------------------------------------------------------------
# The throwaway instance


@dataclass(frozen=True)
class CrowdInstance:
    """What the bench set up: app config (for the server process), batch and invite links."""

    root: Path
    config: dict[str, Any]
    batch_id: int
    items: int
    invite_tokens: list[str]


def _generated_cards(folder: Path, count: int, seed: int) -> list[Path]:
    """``count`` distinct small PNG "cards" (two noisy halves of one texture, 160 x 64 px)."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for index in range(count):
        half = rng.integers(0, 256, size=(64, 76, 3), dtype=np.uint8)
        card = np.concatenate([half, np.full((64, 8, 3), 200, np.uint8), np.roll(half, 3, axis=1)], axis=1)
        path = folder / f"bench-card-{index:05d}.png"
        Image.fromarray(card).save(path)
        paths.append(path)
    return paths


def _app_config(root: Path, database_url: str | None = None) -> dict[str, Any]:
    import secrets

    return {
        "SQLALCHEMY_DATABASE_URI": database_url or f"sqlite:///{root / 'keystone.sqlite3'}",
        "KEYSTONE_DATA_DIR": str(root / "data"),
        "SECRET_KEY": secrets.token_hex(16),
    }


def build_instance(
    root: Path,
    *,
    annotators: int,
    tasks_per_annotator: int,
    n: int = 3,
    kind: str = "judge",
    hold: int = 2,
    gold_cards: int = 5,
    gold_rate: float = 0.1,
    seed: int = 0,
    database_url: str | None = None,
) -> CrowdInstance:
    """Ingest enough generated cards for the load (every worker can finish, holding ``hold``), batch, invite.

    Items: ceil(annotators * (tasks + hold) / n), so slots never run out before every annotator
    has answered ``tasks_per_annotator`` times; plus ``gold_cards`` gold items. ``database_url``
    (default: a SQLite file under ``root``) must name an empty database: the bench owns it.
    """
    from annotation.batches import create_batch
    from annotation.providers import InviteProvider
    from app import create_app
    from app.schema import upgrade
    from catalogue.ingest import ingest
    from core.db import db
    from core.models import Card

    items = math.ceil(annotators * (tasks_per_annotator + hold) / n)
    config = _app_config(root, database_url)
    app = create_app(config, instance_path=root / "instance")
    with app.app_context():
        from sqlalchemy import inspect

        if inspect(db.engine).get_table_names():
            raise click.ClickException(
                f"the bench needs an empty database; {db.engine.url.render_as_string(hide_password=True)} has tables"
            )
        upgrade(db.engine)
        paths = _generated_cards(root / "scans", items + gold_cards, seed)
        report = ingest(
            paths,
            data_dir=Path(config["KEYSTONE_DATA_DIR"]),
            collection_name="bench",
            max_pixels=app.config["KEYSTONE_MAX_PIXELS"],
        )
        if report.rejected:
            raise click.ClickException(f"bench cards were rejected at ingest: {report.rejected[:3]}")
        from sqlalchemy import select

        ids = list(db.session.scalars(select(Card.id).order_by(Card.id)))
        regular, gold_ids = ids[:items], ids[items:]
        gold = {c: _truth(kind, db.session.get(Card, c)) for c in gold_ids}
        batch = create_batch(regular, kind, n, gold_rate, gold=gold)
        tokens = [InviteProvider.invite(f"bench-{i:03d}").token for i in range(annotators)]
        batch_id = batch.id
        db.session.remove()
        db.engine.dispose()
    return CrowdInstance(root, config, batch_id, items, tokens)


def _judge_truth() -> dict[str, bool]:
    """An untouched judge page's answer to the questions every answer has (annotation.questions)."""
    from annotation.questions import judge_questions

    return {q.key: q.default for q in judge_questions() if not q.optional}


def _truth(kind: str, card: Any) -> dict[str, Any]:
    if kind == "judge":
        return _judge_truth()
    half = (card.width - 8) // 2
    return {"left": [2, 2, half - 2, card.height - 2], "right": [half + 10, 2, card.width - 2, card.height - 2]}


def _serve_child() -> None:
    """Child process (``python -m benchmarks.crowd``): the app served on an ephemeral loopback port.

    Reads ``{"config", "instance_path", "threads", "processes"}`` as JSON on stdin, prints the
    port on stdout once listening; :func:`app.serving.serve` picks the server.
    """
    import sys

    from app import create_app
    from app.serving import serve

    setup = json.loads(sys.stdin.readline())
    app = _noop_app if setup.get("noop") else create_app(setup["config"], instance_path=setup["instance_path"])
    serve(
        app,
        "127.0.0.1",
        0,
        threads=setup["threads"],
        processes=setup["processes"],
        on_ready=lambda port: print(port, flush=True),
        with_worker=False,  # the web server alone is measured; a pipeline worker beside it would share its cores
    )


def _noop_app(environ: dict[str, Any], start_response: Callable[..., Any]) -> list[bytes]:
    """A WSGI app that reads the body and answers a fixed JSON document: the harness floor."""
    environ["wsgi.input"].read(int(environ.get("CONTENT_LENGTH") or 0))
    start_response("200 OK", [("Content-Type", "application/json"), ("Content-Length", "28")])
    return [b'{"tasks": [], "answered": 0}']


def harness_burst(clients: int, threads: int | None = None, processes: int | None = None) -> dict[str, float | int | None]:
    """Latency of ``clients`` simultaneous POSTs (one keep-alive connection each, as the annotators
    have) to :func:`_noop_app` served the same way: what this machine and client add to a burst."""
    with ServedApp(None, threads=threads, processes=processes) as served:
        latencies: list[float] = []
        barrier = threading.Barrier(clients)

        def post() -> None:
            client = _Client(served.port)
            try:
                client.request("GET", "/")  # connect, as the invite page does
                barrier.wait(timeout=60)
                latencies.append(client.request("POST", "/crowd/api/next", {"kind": "judge"}, {"X-Crowd-Token": "x" * 120})[2])
            finally:
                client.close()

        threads_ = [threading.Thread(target=post, daemon=True) for _ in range(clients)]
        for thread in threads_:
            thread.start()
        for thread in threads_:
            thread.join(timeout=120)
    return latency_summary(latencies)


class ServedApp:
    """The app served from a child process, for ``with`` use; ``port`` once started."""

    def __init__(self, instance: CrowdInstance | None, threads: int | None = None, processes: int | None = None) -> None:
        """``instance`` None serves :func:`_noop_app` instead of Keystone."""
        self._instance = instance
        self._threads = threads
        self._processes = processes
        self._process: subprocess.Popen[str] | None = None
        self.port = 0

    def __enter__(self) -> Self:
        self._process = subprocess.Popen(
            [sys.executable, "-m", "benchmarks.crowd"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        assert self._process.stdin is not None and self._process.stdout is not None
        setup: dict[str, Any] = {"threads": self._threads, "processes": self._processes}
        if self._instance is None:
            setup["noop"] = True
        else:
            setup.update(config=self._instance.config, instance_path=str(self._instance.root / "instance"))
        self._process.stdin.write(json.dumps(setup) + "\n")
        self._process.stdin.close()
        line = self._process.stdout.readline().strip()
        if not line.isdigit():
            self.__exit__()
            raise click.ClickException(f"the bench server did not start (it printed {line!r})")
        self.port = int(line)
        return self

    def cpu_seconds(self) -> float | None:
        """User + system CPU the server's processes have used so far (Linux /proc; None elsewhere).

        All processes of the server's process group count (gunicorn's workers as well as its
        master). Unlike latency, this does not grow when other programs compete for the cores.
        """
        if self._process is None or not Path("/proc/self/stat").exists():
            return None
        ticks = 0
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue  # a process that ended meanwhile
            if int(fields[2]) == self._process.pid:  # pgrp: the child leads its own session
                ticks += int(fields[11]) + int(fields[12])  # utime, stime in clock ticks
        return ticks / os.sysconf("SC_CLK_TCK")

    def __exit__(self, *_: object) -> None:
        if self._process is None:
            return
        self._process.terminate()  # gunicorn's master stops its workers on SIGTERM
        try:
            self._process.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self._process.pid, signal.SIGKILL)
            self._process.wait(10)
        if self._process.stdout is not None:
            self._process.stdout.close()
        self._process = None


# ---------------------------------------------------------------------------------------------
# The simulated annotators


@dataclass
class AnnotatorLog:
    """What one simulated annotator saw: latencies in ms, acknowledged answer ids, statuses."""

    fetch_ms: list[float] = field(default_factory=list)
    submit_ms: list[float] = field(default_factory=list)
    acknowledged: list[int] = field(default_factory=list)
    statuses: list[int] = field(default_factory=list)
    replays: int = 0
    replays_ok: int = 0
    errors: list[str] = field(default_factory=list)
    stopped: str = ""


class _Client:
    """One keep-alive HTTP/1.1 connection; reconnects once if the server closed it."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.connection = http.client.HTTPConnection("127.0.0.1", port, timeout=60)

    def request(
        self, method: str, path: str, body: Any = None, headers: dict[str, str] | None = None
    ) -> tuple[int, bytes, float]:
        data = json.dumps(body).encode() if body is not None else None
        headers = {**(headers or {}), **({"Content-Type": "application/json"} if data is not None else {})}
        for attempt in (0, 1):
            start = time.perf_counter()
            try:
                self.connection.request(method, path, body=data, headers=headers)
                response = self.connection.getresponse()
                payload = response.read()
            except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError):
                # Keep-alive race: the server closed an idle connection as we reused it.
                self.connection.close()
                self.connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=60)
                if attempt:
                    raise
                continue
            return response.status, payload, (time.perf_counter() - start) * 1000.0
        raise AssertionError("unreachable")

    def close(self) -> None:
        self.connection.close()


def _answer_for(kind: str, task: dict[str, Any], rng: random.Random) -> dict[str, Any]:
    """A plausible answer: the truth for judgements; boxes around each half jittered by a few pixels."""
    if kind == "judge":
        return _judge_truth()
    width, height = int(task["card_width"]), int(task["card_height"])
    half = (width - 8) // 2

    def jitter(box: Sequence[int]) -> list[int]:
        x0, y0, x1, y1 = (v + rng.randint(-2, 2) for v in box)
        return [max(0, x0), max(0, y0), min(width, x1), min(height, y1)]

    return {"left": jitter([2, 2, half - 2, height - 2]), "right": jitter([half + 10, 2, width - 2, height - 2])}


def run_annotator(
    port: int,
    invite_token: str,
    kind: str,
    tasks: int,
    think_s: tuple[float, float],
    seed: int,
    start: threading.Barrier | None = None,
    replay_every: int = REPLAY_EVERY,
    arrive_after_s: float = 0.0,
) -> AnnotatorLog:
    """Open the invite page, wait for the start line and ``arrive_after_s`` more, then fetch-next /
    think / submit until ``tasks`` answers are acknowledged."""
    log = AnnotatorLog()
    rng = random.Random(seed)
    client = _Client(port)
    try:
        status, page, _ = client.request("GET", f"/crowd/invite/{invite_token}")
        match = _WORKER_TOKEN.search(page.decode("utf-8", "replace"))
        if status != 200 or match is None or not match.group(1):
            log.stopped = f"invite page answered {status}"
            log.statuses.append(status)
            return log
        headers = {"X-Crowd-Token": match.group(1)}
        if start is not None:
            start.wait()
        time.sleep(arrive_after_s)
        waits = 0
        while len(log.acknowledged) < tasks:
            status, body, ms = client.request("POST", "/crowd/api/next", {"kind": kind}, headers)
            log.fetch_ms.append(ms)
            log.statuses.append(status)
            if status != 200:
                log.stopped = f"fetch-next answered {status}: {body[:200]!r}"
                return log
            document = json.loads(body)
            if not document["tasks"]:
                if document["reason"] == "all_reserved" and waits < ALL_RESERVED_RETRIES:
                    waits += 1
                    time.sleep(0.05)
                    continue
                log.stopped = f"no task: {document['reason']}"
                return log
            task = document["tasks"][0]
            time.sleep(rng.uniform(*think_s))
            submission = {
                "token": task["token"],
                "answer": _answer_for(kind, task, rng),
                "key": f"bench-{seed}-{len(log.acknowledged):05d}-{rng.getrandbits(48):012x}",
            }
            status, body, ms = client.request("POST", "/crowd/api/submit", submission, headers)
            log.submit_ms.append(ms)
            log.statuses.append(status)
            if status != 201:
                log.stopped = f"submit answered {status}: {body[:200]!r}"
                return log
            stored = json.loads(body)["answer"]
            log.acknowledged.append(int(stored))
            if replay_every and len(log.acknowledged) % replay_every == 0:
                status, body, _ = client.request("POST", "/crowd/api/submit", submission, headers)
                log.statuses.append(status)
                log.replays += 1
                replay = json.loads(body) if status < 500 else {}
                log.replays_ok += status == 200 and replay.get("answer") == stored and replay.get("duplicate") is True
        log.stopped = "done"
    except (OSError, http.client.HTTPException, ValueError, KeyError) as exc:
        log.errors.append(f"{type(exc).__name__}: {exc}")
        log.stopped = "client error"
    finally:
        client.close()
    return log


def latency_summary(values_ms: Sequence[float]) -> dict[str, float | int | None]:
    """Count, p50, p95 and max in milliseconds (linear-interpolated percentiles); None when empty."""
    if not values_ms:
        return {"count": 0, "p50_ms": None, "p95_ms": None, "max_ms": None}
    values = np.asarray(values_ms, dtype=float)
    return {
        "count": int(values.size),
        "p50_ms": round(float(np.percentile(values, 50)), 2),
        "p95_ms": round(float(np.percentile(values, 95)), 2),
        "max_ms": round(float(values.max()), 2),
    }


def _stored_figures(instance: CrowdInstance, acknowledged: set[int]) -> dict[str, int]:
    """Ground truth from the database: lost, unacknowledged, duplicated and over-capacity answers."""
    from sqlalchemy import func, select

    from annotation.models import Answer, Batch, BatchItem, Reservation
    from app import create_app
    from core.db import db, utcnow

    app = create_app(instance.config, instance_path=instance.root / "instance")
    with app.app_context():
        batch = db.session.get(Batch, instance.batch_id)
        assert batch is not None
        rows = db.session.execute(
            select(Answer.id, Answer.item_id, Answer.worker_id, BatchItem.is_gold)
            .join(BatchItem, Answer.item_id == BatchItem.id)
            .where(BatchItem.batch_id == instance.batch_id)
        ).all()
        now = utcnow()
        held = dict(
            db.session.execute(
                select(Reservation.item_id, func.count())
                .join(BatchItem, Reservation.item_id == BatchItem.id)
                .where(BatchItem.batch_id == instance.batch_id, Reservation.answered_at.is_(None), Reservation.expires_at > now)
                .group_by(Reservation.item_id)
            ).all()
        )
        n = batch.answers_per_item
        db.session.remove()
        db.engine.dispose()
    stored = {r.id for r in rows}
    pairs = [(r.item_id, r.worker_id) for r in rows]
    per_item: dict[int, int] = {}
    for r in rows:
        if not r.is_gold:  # gold is deliberately not capped at N
            per_item[r.item_id] = per_item.get(r.item_id, 0) + 1
    return {
        "answers_stored": len(stored),
        "lost": len(acknowledged - stored),
        "unacknowledged": len(stored - acknowledged),
        "duplicates": len(pairs) - len(set(pairs)),
        "over_capacity_items": sum(1 for item, count in per_item.items() if count + held.get(item, 0) > n),
    }


def run_crowd_bench(
    annotators: int = 50,
    tasks_per_annotator: int = 10,
    *,
    kind: str = "judge",
    n: int = 3,
    think_ms: tuple[float, float] = (250.0, 750.0),
    ramp_s: float = DEFAULT_RAMP_S,
    server_threads: int | None = None,
    server_processes: int | None = None,
    seed: int = 0,
    replay_every: int = REPLAY_EVERY,
    root: Path | None = None,
    database_url: str | None = None,
    on_progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Set up, serve, run ``annotators`` concurrent annotators, check the database; one JSON-able report.

    ``think_ms`` is the (min, max) of the uniform time an annotator looks at a task before
    answering; (0, 0) measures the server saturated (latency then reflects queueing, i.e.
    concurrency divided by throughput, not the cost of one request). Every ``replay_every``-th
    submit of an annotator is posted twice (0: never). Annotators arrive one after another
    over ``ramp_s`` seconds (0: all at the same instant, a burst no real crowd makes; the
    report then also has ``harness_burst``, the same burst against a WSGI app that does
    nothing, which is what the machine and this client add by themselves). ``root`` (default:
    a temporary folder, removed afterwards) holds the throwaway database and data dir;
    ``database_url`` puts the catalogue in another, empty database instead (PostgreSQL).
    """
    from app.serving import default_processes, default_threads, describe

    say = on_progress or (lambda _message: None)
    server_processes = default_processes() if server_processes is None else server_processes
    server_threads = default_threads(server_processes) if server_threads is None else server_threads
    owned = root is None
    root = Path(tempfile.mkdtemp(prefix="keystone-bench-crowd-")) if root is None else root
    try:
        say(f"setting up {annotators} annotators x {tasks_per_annotator} tasks in {root}")
        instance = build_instance(
            root,
            annotators=annotators,
            tasks_per_annotator=tasks_per_annotator,
            n=n,
            kind=kind,
            seed=seed,
            database_url=database_url,
        )
        logs: list[AnnotatorLog] = [AnnotatorLog() for _ in range(annotators)]
        think_s = (think_ms[0] / 1000.0, think_ms[1] / 1000.0)
        with ServedApp(instance, threads=server_threads, processes=server_processes) as served:
            say(f"serving on 127.0.0.1:{served.port} ({describe(server_processes, server_threads)})")
            barrier = threading.Barrier(annotators + 1)

            def work(index: int) -> None:
                logs[index] = run_annotator(
                    served.port,
                    instance.invite_tokens[index],
                    kind,
                    tasks_per_annotator,
                    think_s,
                    seed * 100_003 + index,
                    barrier,
                    replay_every,
                    arrive_after_s=ramp_s * index / max(1, annotators - 1),
                )

            threads = [threading.Thread(target=work, args=(i,), daemon=True) for i in range(annotators)]
            for thread in threads:
                thread.start()
            try:
                barrier.wait(timeout=120)
            except threading.BrokenBarrierError:
                pass  # an annotator stopped before the start line (its log says why)
            cpu_before = served.cpu_seconds()
            started = time.perf_counter()
            for thread in threads:
                thread.join(timeout=600)
            seconds = time.perf_counter() - started
            cpu_after = served.cpu_seconds()
        acknowledged = {a for log in logs for a in log.acknowledged}
        figures = _stored_figures(instance, acknowledged)
        floor = harness_burst(annotators, server_threads, server_processes) if ramp_s == 0 else None
    finally:
        if owned:
            shutil.rmtree(root, ignore_errors=True)
    fetch = [ms for log in logs for ms in log.fetch_ms]
    submits = [ms for log in logs for ms in log.submit_ms]
    statuses = [s for log in logs for s in log.statuses]
    stops: dict[str, int] = {}
    for log in logs:
        stops[log.stopped] = stops.get(log.stopped, 0) + 1
    # Each annotator's first fetch reserves two tasks (the one shown and the preloaded next);
    # with ramp_s = 0 all of them at the same instant: reported apart from the steady state.
    first = [log.fetch_ms[0] for log in logs if log.fetch_ms]
    steady = [ms for log in logs for ms in log.fetch_ms[1:]]
    report: dict[str, Any] = {
        "annotators": annotators,
        "tasks_per_annotator": tasks_per_annotator,
        "kind": kind,
        "answers_per_item": n,
        "items": instance.items,
        "think_ms": list(think_ms),
        "ramp_s": ramp_s,
        "server": describe(server_processes, server_threads),
        "server_processes": server_processes,
        "server_threads": server_threads,
        "database": (database_url or "sqlite").split(":", 1)[0].split("+", 1)[0],
        "seconds": round(seconds, 3),
        "requests": len(statuses),
        "throughput_rps": round(len(fetch) / seconds + len(submits) / seconds, 1) if seconds else None,
        # Server CPU per API request (fetch-next, submit, replays): the cost of a request, free
        # of the queueing that latency includes on a busy machine.
        "server_cpu_ms_per_request": (
            round((cpu_after - cpu_before) * 1000 / len(statuses), 2)
            if cpu_before is not None and cpu_after is not None and statuses
            else None
        ),
        "fetch_next": latency_summary(fetch),
        "submit": latency_summary(submits),
        "fetch_next_first": latency_summary(first),
        "fetch_next_steady": latency_summary(steady),
        "answers_submitted": sum(len(log.acknowledged) for log in logs),
        **figures,
        "replays": sum(log.replays for log in logs),
        "replays_ok": sum(log.replays_ok for log in logs),
        "status_5xx": sum(1 for s in statuses if s >= 500),
        "status_4xx": sum(1 for s in statuses if 400 <= s < 500),
        "client_errors": [e for log in logs for e in log.errors][:10],
        "stopped": stops,
        "target_p95_ms": TARGET_P95_MS,
        **({"harness_burst": floor} if floor is not None else {}),
    }
    p95s = [report[k]["p95_ms"] for k in ("fetch_next", "submit")]
    report["meets_target"] = all(p is not None and p < TARGET_P95_MS for p in p95s)
    return report


@click.command("crowd")
@click.option(
    "--annotators",
    default=50,
    show_default=True,
    type=click.IntRange(1, 90),
    help="Concurrent simulated annotators (threads, one keep-alive connection each).",
)
@click.option(
    "--tasks-per-annotator",
    default=10,
    show_default=True,
    type=click.IntRange(1, 1000),
    help="Answers each annotator gives before leaving.",
)
@click.option("--kind", type=click.Choice(("judge", "crop")), default="judge", show_default=True)
@click.option("--n", "n", default=3, show_default=True, type=click.IntRange(1, 20), help="Answers per item.")
@click.option(
    "--think-ms",
    nargs=2,
    type=click.FloatRange(0, 60_000),
    default=(250.0, 750.0),
    show_default=True,
    help="Min and max of an annotator's uniform thinking time per task; 0 0 saturates the server.",
)
@click.option(
    "--ramp-s",
    default=DEFAULT_RAMP_S,
    show_default=True,
    type=click.FloatRange(0, 600),
    help="Annotators arrive evenly over this many seconds; 0 starts them all at the same instant "
    "and also measures that burst against an app that does nothing.",
)
@click.option(
    "--server-processes",
    type=click.IntRange(1, 16),
    default=None,
    help="Server processes, as keystone serve --processes [default: keystone serve's].",
)
@click.option(
    "--server-threads",
    type=click.IntRange(1, 64),
    default=None,
    help="Threads per server process, as keystone serve --threads [default: keystone serve's].",
)
@click.option("--seed", default=0, show_default=True, type=int)
@click.option(
    "--database-url",
    default=None,
    metavar="URL",
    help="An empty database for the bench's catalogue, e.g. postgresql+psycopg://user@host/db "
    "[default: a throwaway SQLite file].",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_crowd_command(
    annotators: int,
    tasks_per_annotator: int,
    kind: str,
    n: int,
    think_ms: tuple[float, float],
    ramp_s: float,
    server_processes: int | None,
    server_threads: int | None,
    seed: int,
    database_url: str | None,
    as_json: bool,
) -> None:
    """Latency of fetch-next and submit with concurrent annotators over real HTTP (SQLite by default,
    or an empty PostgreSQL database with --database-url; waitress, or gunicorn with --server-processes above 1).

    Exits 1 when an answer was lost or duplicated or a 5xx occurred (the p95 target is reported, not enforced).
    """
    if think_ms[0] > think_ms[1]:
        raise click.BadParameter(f"expected min <= max, got {think_ms[0]:g} > {think_ms[1]:g}", param_hint="--think-ms")
    report = run_crowd_bench(
        annotators,
        tasks_per_annotator,
        kind=kind,
        n=n,
        think_ms=think_ms,
        ramp_s=ramp_s,
        server_threads=server_threads,
        server_processes=server_processes,
        seed=seed,
        database_url=database_url,
        on_progress=None if as_json else (lambda m: click.echo(m, err=True)),
    )
    broken = (
        report["lost"]
        or report["unacknowledged"]
        or report["duplicates"]
        or report["over_capacity_items"]
        or report["status_5xx"]
        or report["client_errors"]
        or report["replays_ok"] != report["replays"]
    )
    if as_json:
        click.echo(json.dumps(report, indent=2))
    else:
        click.echo(
            f"{annotators} annotators x {tasks_per_annotator} {kind} tasks, arriving over {ramp_s:g} s, "
            f"think {think_ms[0]:g}-{think_ms[1]:g} ms, {report['server']}: {report['seconds']:.1f} s, "
            f"{report['throughput_rps']} requests/s, server CPU {report['server_cpu_ms_per_request']} ms "
            "per request"
        )
        for name in ("fetch_next", "fetch_next_first", "fetch_next_steady", "submit"):
            row = report[name]
            click.echo(f"  {name:<17} n={row['count']:<5} p50 {row['p50_ms']} ms  p95 {row['p95_ms']} ms  max {row['max_ms']} ms")
        if "harness_burst" in report:
            row = report["harness_burst"]
            click.echo(
                f"  the same burst against an app that does nothing: p50 {row['p50_ms']} ms  "
                f"p95 {row['p95_ms']} ms  max {row['max_ms']} ms"
            )
        click.echo(
            f"  answers: {report['answers_submitted']} acknowledged, {report['answers_stored']} stored, "
            f"{report['lost']} lost, {report['duplicates']} duplicated, {report['over_capacity_items']} items "
            f"over N; replays {report['replays_ok']}/{report['replays']} ok; 5xx {report['status_5xx']}"
        )
        click.echo(f"  p95 target < {TARGET_P95_MS:g} ms: {'met' if report['meets_target'] else 'NOT met'}")
    if broken:
        raise SystemExit(1)


if __name__ == "__main__":
    _serve_child()
