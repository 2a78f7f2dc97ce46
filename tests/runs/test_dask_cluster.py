"""``keystone run --executor dask --scheduler ADDR`` against a real scheduler and worker processes.

The cluster is the one an operator starts (``dask scheduler``, ``dask worker``), on 127.0.0.1:
the driver sends cards out in a bounded window and alone writes the database. Outcomes must
equal the local process pool's, and a worker killed mid-run costs only its cards in flight,
which the scheduler hands to another worker.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from PIL import Image

pytest.importorskip("distributed", reason="the cluster path needs dask[distributed] (the 'cluster' extra)")

STAGES = "filter,orientation,rectify,disparity,grade"
SCHEDULER_AT = re.compile(r"Scheduler at:\s+(tcp://127\.0\.0\.1:\d+)")


@pytest.fixture(scope="module")
def scans(tmp_path_factory: pytest.TempPathFactory, mount_pair) -> Path:  # type: ignore[no-untyped-def]
    """Six stereo cards cut from the Motorcycle pair at different places (six content hashes)."""
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    folder = tmp_path_factory.mktemp("scans")
    for index in range(6):
        x0, y0 = 40 * index, 12 * index
        crop = (slice(y0, y0 + 360), slice(x0, x0 + 480))
        Image.fromarray(mount_pair(left[crop], right[crop])).save(folder / f"card{index}.png")
    return folder


def _spawn(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "dask", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=env,
    )


def _stop(process: subprocess.Popen[str]) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


class Cluster:
    def __init__(self) -> None:
        self.scheduler = _spawn("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard")
        assert self.scheduler.stderr is not None
        self.address = ""
        deadline = time.monotonic() + 60
        while not self.address and time.monotonic() < deadline:
            line = self.scheduler.stderr.readline()
            assert line, f"the dask scheduler stopped (exit {self.scheduler.poll()})"
            if match := SCHEDULER_AT.search(line):
                self.address = match.group(1)
        assert self.address, "the dask scheduler did not say where it listens within 60 s"
        # The scheduler keeps logging; nobody reads it after start-up, so let it write nowhere.
        self.scheduler.stderr.close()
        self.workers: list[subprocess.Popen[str]] = []

    def add_worker(self) -> subprocess.Popen[str]:
        # Workers import the project's pipeline by name, as they would on a cluster node
        # where the project is installed; without the thread variables an inline run in this
        # process may have set (a node's worker would not have them).
        from pipeline.runner import ONE_THREAD_ENVIRONMENT

        env = {k: v for k, v in os.environ.items() if k not in ONE_THREAD_ENVIRONMENT}
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(Path.cwd()), os.environ.get("PYTHONPATH")]))
        worker = _spawn(
            "worker",
            self.address,
            "--host",
            "127.0.0.1",
            "--nworkers",
            "1",
            "--nthreads",
            "1",
            "--no-dashboard",
            "--memory-limit",
            "2GiB",
            env=env,
        )
        assert worker.stderr is not None
        worker.stderr.close()
        self.workers.append(worker)
        return worker

    def wait_for_workers(self, count: int) -> None:
        from distributed import Client

        with Client(self.address, timeout=30) as client:
            client.wait_for_workers(count, timeout=90)

    def close(self) -> None:
        for worker in self.workers:
            _stop(worker)
        _stop(self.scheduler)


@pytest.fixture
def cluster() -> Iterator[Cluster]:
    cluster = Cluster()
    try:
        for _ in range(2):
            cluster.add_worker()
        cluster.wait_for_workers(2)
        yield cluster
    finally:
        cluster.close()


def _keystone(instance: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(instance)}
    env.pop("KEYSTONE_DATABASE_URL", None)
    env.pop("KEYSTONE_DATA_DIR", None)
    result = subprocess.run([sys.executable, "-m", "app", *args], env=env, capture_output=True, text=True, timeout=600)
    if check:
        assert result.returncode == 0, result.stderr[-3000:]
    return result


def _decide_orientation(instance: Path) -> None:
    """A curator's override on every card (upright, positive, eyes in order: how the test cards
    were made), so the flow rule lets them through rectification whatever the step says."""
    import sqlite3

    with sqlite3.connect(instance / "keystone.sqlite3") as connection:
        connection.execute(
            "INSERT INTO orientation_overrides (card_id, upside_down, inverted, swapped, note, updated_at) "
            "SELECT id, 0, 0, 0, 'test: made upright', CURRENT_TIMESTAMP FROM cards"
        )


def _outcomes(instance: Path) -> dict[str, dict[str, tuple]]:
    """Per card file and stage: status, outcome, reason and the grade's measurements rounded."""
    cards = json.loads(_keystone(instance, "cards", "--json").stdout)["cards"]
    table: dict[str, dict[str, tuple]] = {}
    for card in cards:
        row = {}
        for stage in STAGES.split(","):
            entry = card["stages"][stage]
            metrics = entry.get("metrics") or {}
            row[stage] = (
                entry["status"],
                entry.get("outcome"),
                entry.get("reason"),
                metrics.get("good_match_fraction"),
                metrics.get("grade"),
            )
        table[card["source"]] = row
    return table


def test_dask_cluster_gives_the_local_pools_outcomes(tmp_path, scans, cluster):
    local, remote = tmp_path / "local", tmp_path / "remote"
    for instance in (local, remote):
        _keystone(instance, "ingest", str(scans), "--json")
        _decide_orientation(instance)
    _keystone(local, "run", "--stages", STAGES, "--workers", "2", "--json")
    report = json.loads(
        _keystone(remote, "run", "--stages", STAGES, "--executor", "dask", "--scheduler", cluster.address, "--json").stdout
    )
    assert [stage["processed"] for stage in report["stages"]][0] == 6
    assert all(stage["failed"] == 0 for stage in report["stages"]), report
    expected, got = _outcomes(local), _outcomes(remote)
    assert set(got) == {f"card{index}.png" for index in range(6)}
    assert got == expected
    assert all(row["grade"][0] == "done" for row in got.values())


def test_a_worker_killed_mid_run_costs_only_its_cards_in_flight(tmp_path, scans, cluster):
    from distributed import Client

    instance = tmp_path / "instance"
    _keystone(instance, "ingest", str(scans), "--json")
    _decide_orientation(instance)
    env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(instance)}
    run = subprocess.Popen(
        [sys.executable, "-m", "app", "run", "--stages", STAGES, "--executor", "dask", "--scheduler", cluster.address, "--json"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    victim = cluster.workers[0]
    killed_with_work = False
    with Client(cluster.address, timeout=30) as client:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and run.poll() is None:
            processing = client.processing()
            busy = [address for address, keys in processing.items() if keys]
            if len(busy) == 2:  # both workers hold a card: kill one of them with its card in flight
                os.killpg(victim.pid, signal.SIGKILL)
                killed_with_work = True
                break
            time.sleep(0.05)
        cluster.add_worker()  # the cluster heals, as an autoscaler would; the run does not wait for it
    out, err = run.communicate(timeout=600)
    assert run.returncode == 0, err[-3000:]
    assert killed_with_work, "the run finished before both workers were busy"
    report = json.loads(out)
    assert all(stage["failed"] == 0 for stage in report["stages"]), report
    statuses = _outcomes(instance)
    assert all(row[stage][0] == "done" for row in statuses.values() for stage in STAGES.split(","))


def _blas_threads(info: list[dict]) -> set[int]:
    return {library["num_threads"] for library in info if library["user_api"] == "blas"}


def test_every_worker_runs_one_opencv_and_one_blas_thread_those_joining_later_too(cluster):
    """The driver's executor registers the worker set-up a local pool worker gets; a worker
    that joins afterwards gets it as well (a dask worker left alone would use every core)."""
    import cv2
    import threadpoolctl
    from distributed import Client

    from runs.executors import make_executor

    with Client(cluster.address, timeout=30) as client:
        before = client.run(cv2.getNumThreads)
    with make_executor("dask", 0, cluster.address):
        pass
    cluster.add_worker()
    cluster.wait_for_workers(3)
    with Client(cluster.address, timeout=30) as client:
        opencv = client.run(cv2.getNumThreads)
        blas = client.run(threadpoolctl.threadpool_info)
    assert len(opencv) == 3 and set(opencv.values()) == {1}, (before, opencv)
    assert all(_blas_threads(info) == {1} for info in blas.values()), blas


def test_the_window_follows_the_cluster_as_workers_join(cluster):
    """Two single-threaded workers give four cards in flight; a third joining gives six, read
    again from the scheduler (at most every WINDOW_RECHECK_S in a run)."""
    from distributed import Client

    from runs.executors import dispatch_window, worker_threads

    with Client(cluster.address, timeout=30) as client:
        executor = client.get_executor()
        assert worker_threads(executor) == 2
        window = dispatch_window(executor, recheck_s=0)
        assert callable(window) and window() == 4
        cluster.add_worker()
        cluster.wait_for_workers(3)
        assert window() == 6


WIDE_WORKERS = 24  # more than the old fixed window of 16
SLEEP_S = 2.0


def sleep_and_say_where(task, *, param_hash: str):  # type: ignore[no-untyped-def]
    """A card that sleeps and records the worker it ran on and when (wall clock: one machine)."""
    from distributed import get_worker

    from pipeline.records import StageRecord

    start = time.time()
    time.sleep(SLEEP_S)
    return StageRecord(
        card_id=task.card_id,
        stage="filter",
        param_hash=param_hash,
        status="done",
        outcome="pass",
        metrics={"worker": get_worker().address, "start": start, "end": time.time()},
    )


def _most_busy_at_once(records) -> int:  # type: ignore[no-untyped-def]
    """The most distinct workers running a card at one instant (checked at every card's start)."""
    spans = [(r.metrics["worker"], r.metrics["start"], r.metrics["end"]) for r in records]
    return max(len({worker for worker, start, end in spans if start <= t < end}) for _, t, _ in spans)


@pytest.fixture(scope="module")
def wide_cluster() -> Iterator[tuple[object, float]]:
    """24 single-threaded worker processes (each with its nanny) on loopback, and the seconds they took to start."""
    from distributed import LocalCluster

    clock = time.monotonic()
    cluster = LocalCluster(n_workers=WIDE_WORKERS, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None)
    try:
        from distributed import Client

        with Client(cluster.scheduler_address, timeout=30) as client:
            client.wait_for_workers(WIDE_WORKERS, timeout=240)
        yield cluster, time.monotonic() - clock
    finally:
        cluster.close()


def test_the_driver_keeps_24_workers_busy_at_once(app, data_dir, wide_cluster):
    """`keystone run`'s loop on a cluster wider than the old window: 72 cards that sleep 2 s,
    through run_stage (planning, claims, writes) on 24 workers. Every worker gets a card, all
    24 run one at the same instant, and the driver holds 48 in flight (two per thread). The
    same cards through the old fixed window of 16 keep at most 16 busy."""
    import dataclasses
    import functools

    from benchmarks.driver import NoOpParams, fill_catalogue
    from pipeline.records import CardTask, param_hash
    from pipeline.runner import run_tasks
    from runs.executors import make_executor
    from runs.loop import run_stage
    from runs.specs import available_stages

    cluster, start_s = wide_cluster
    print(f"{WIDE_WORKERS}-worker LocalCluster started in {start_s:.1f} s")
    params = NoOpParams(bench="wide-cluster")
    task = functools.partial(sleep_and_say_where, param_hash=param_hash(params))
    with app.app_context():
        spec = dataclasses.replace(available_stages()["filter"], params=params, task=task)
        fill_catalogue(3 * WIDE_WORKERS)
        records = []
        with make_executor("dask", 0, cluster.scheduler_address) as executor:
            report = run_stage(spec, data_dir=data_dir, executor=executor, on_record=records.append)
            old = list(
                run_tasks(
                    task,
                    [CardTask(card_id=i, content_hash="0" * 64, image_path="", work_dir="", data_dir="") for i in range(32)],
                    executor,
                    stage="filter",
                    param_hash="old-window",
                    window=16,
                )
            )
    assert report.processed == 3 * WIDE_WORKERS and report.failed == 0, report.failures
    assert report.flight.window == 2 * WIDE_WORKERS and report.flight.most == 2 * WIDE_WORKERS
    assert len({r.metrics["worker"] for r in records}) == WIDE_WORKERS
    assert _most_busy_at_once(records) == WIDE_WORKERS
    assert _most_busy_at_once(old) == 16
