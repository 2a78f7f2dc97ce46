"""The executor seam: inline and process-pool runs give the same records; errors stay per card."""

from __future__ import annotations

import functools
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass

import pytest

from pipeline.records import CardTask, StageRecord, param_hash
from pipeline.runner import InFlight, RestartingProcessPool, in_flight_window, run_tasks


def _square_task(task: CardTask) -> StageRecord:
    return StageRecord(card_id=task.card_id, stage="test", param_hash="p", status="done", metrics={"square": task.card_id**2})


def _crash_on_three(task: CardTask) -> StageRecord:
    if task.card_id == 3:
        os._exit(1)  # a worker dying in native code
    return _square_task(task)


def _tasks(n: int) -> list[CardTask]:
    return [
        CardTask(card_id=i, content_hash=f"{i:064x}", image_path="/nonexistent", work_dir="/tmp", data_dir="/tmp")
        for i in range(n)
    ]


def test_inline_and_pools_agree():
    inline = sorted((r.card_id, r.metrics["square"]) for r in run_tasks(_square_task, _tasks(20), stage="test", param_hash="p"))
    with ThreadPoolExecutor(3) as threads:
        threaded = sorted(
            (r.card_id, r.metrics["square"])
            for r in run_tasks(_square_task, _tasks(20), threads, stage="test", param_hash="p", window=4)
        )
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        pooled = sorted(
            (r.card_id, r.metrics["square"]) for r in run_tasks(_square_task, _tasks(20), pool, stage="test", param_hash="p")
        )
    assert inline == threaded == pooled == [(i, i * i) for i in range(20)]


def test_the_window_is_two_cards_per_worker_thread():
    """The card a thread computes and the next one, already sent (pipeline.runner.WINDOW_PER_THREAD)."""
    assert [in_flight_window(threads) for threads in (1, 2, 24, 32)] == [2, 4, 48, 64]
    assert in_flight_window(0) == 2  # a cluster with no worker yet: cards wait at its scheduler
    assert in_flight_window(8, per_thread=3) == 24
    with pytest.raises(ValueError, match="per_thread"):
        in_flight_window(8, per_thread=0)


def _held_task(task: CardTask, state: dict) -> StageRecord:
    """Counts the tasks running at once in a thread pool and holds each until ``state["release"]``
    is set (or for ``state["hold_s"]``)."""
    with state["lock"]:
        state["running"] += 1
        state["most"] = max(state["most"], state["running"])
        if state["running"] >= state["release_at"]:
            state["release"].set()
    released = state["release"].wait(state["hold_s"])
    with state["lock"]:
        state["running"] -= 1
        state["timed_out"] += not released
    return _square_task(task)


def _hold_state(release_at: int, hold_s: float) -> dict:
    import threading

    return {
        "lock": threading.Lock(),
        "running": 0,
        "most": 0,
        "release": threading.Event(),
        "release_at": release_at,
        "hold_s": hold_s,
        "timed_out": 0,
    }


def test_run_tasks_keeps_the_window_full_and_no_fuller():
    state = _hold_state(release_at=5, hold_s=5.0)
    flight = InFlight()
    with ThreadPoolExecutor(12) as threads:
        records = list(
            run_tasks(
                functools.partial(_held_task, state=state),
                _tasks(40),
                threads,
                stage="test",
                param_hash="p",
                window=5,
                flight=flight,
            )
        )
    assert sorted(r.card_id for r in records) == list(range(40))
    # Twelve threads could run twelve at once; the window lets five out, and keeps five out.
    assert state["most"] == 5 and flight.most == 5 and flight.window == 5
    assert flight.submitted == 40 and flight.first_submit <= flight.last_submit


def test_a_window_that_grows_is_read_again_while_the_run_waits(monkeypatch):
    """A dask cluster's window grows as workers join (runs.executors.dispatch_window): the run
    asks again every WINDOW_RECHECK_S even when no card finishes. Here the first cards finish
    only once six run at once, which they can only do after the window has grown to six."""
    import time

    import pipeline.runner

    monkeypatch.setattr(pipeline.runner, "WINDOW_RECHECK_S", 0.05)
    # No card is let go by the clock: the hold is far longer than any slow machine needs.
    state = _hold_state(release_at=6, hold_s=120.0)
    began = time.monotonic()

    def window() -> int:
        return 2 if time.monotonic() - began < 0.2 else 6

    flight = InFlight()
    with ThreadPoolExecutor(12) as threads:
        records = list(
            run_tasks(
                functools.partial(_held_task, state=state),
                _tasks(12),
                threads,
                stage="test",
                param_hash="p",
                window=window,
                flight=flight,
            )
        )
    assert len(records) == 12
    # Six ran at once and let each other go: the run read the window again while it waited.
    assert state["release"].is_set() and state["timed_out"] == 0
    assert flight.window == 6 and flight.most == 6


_POOL_WORKER_THREADS = """
import json, os, cv2, threadpoolctl
from pipeline.runner import RestartingProcessPool
with RestartingProcessPool(1) as pool:
    opencv = pool.submit(cv2.getNumThreads).result()
    blas = pool.submit(threadpoolctl.threadpool_info).result()
    environment = pool.submit(os.getenv, "OPENBLAS_NUM_THREADS").result()
print(json.dumps([opencv, sorted({i["num_threads"] for i in blas if i["user_api"] == "blas"}), environment]))
"""


def test_a_pool_worker_runs_one_opencv_and_one_blas_thread():
    """Cards are the unit of parallelism: threads inside a worker only add their overhead. Run
    from a fresh interpreter without the thread variables (an inline run earlier in this process
    sets them, and a pool would inherit them)."""
    import json
    import subprocess
    import sys

    from pipeline.runner import ONE_THREAD_ENVIRONMENT

    env = {k: v for k, v in os.environ.items() if k not in ONE_THREAD_ENVIRONMENT}
    result = subprocess.run([sys.executable, "-c", _POOL_WORKER_THREADS], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    opencv, blas, environment = json.loads(result.stdout.strip().splitlines()[-1])
    assert opencv == 1 and blas == [1]
    assert environment == "1"  # for BLAS libraries loaded later (scipy's own)


_CARD_LIKE_ALLOCATIONS = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from pipeline.runner import keep_freed_memory
    assert keep_freed_memory()
def card(side):
    scan = np.ones((side, 2 * side, 3), np.uint8)
    working = scan[:, :side].astype(np.float32)
    reduced = np.ascontiguousarray(scan[::2, ::2])
    return int(working[0, 0, 0]) + int(reduced[0, 0, 0])
card(1200)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for i in range(20):
    card((1000, 1200, 1400)[i % 3])
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def test_a_worker_keeps_freed_memory_for_the_next_card():
    """Page faults (the kernel zeroing pages glibc handed back) over twenty card-sized rounds of
    allocations: a worker's setting keeps most of them away (measured 4,331 -> 1,454)."""
    import platform
    import subprocess
    import sys

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("mallopt is glibc's (Linux)")
    faults = {
        mode: int(
            subprocess.run(
                [sys.executable, "-c", _CARD_LIKE_ALLOCATIONS, mode], capture_output=True, text=True, check=True
            ).stdout
        )
        for mode in ("plain", "keep")
    }
    assert faults["keep"] < faults["plain"] / 2, faults


def test_a_dead_worker_fails_only_cards_in_flight_and_the_batch_goes_on():
    with RestartingProcessPool(1) as pool:
        records = list(run_tasks(_crash_on_three, _tasks(6), pool, stage="test", param_hash="p", window=1))
        assert pool.restarts == 1
    by_card = {r.card_id: r for r in records}
    assert set(by_card) == set(range(6))
    assert by_card[3].status == "failed" and by_card[3].reason.startswith("worker_crashed")
    assert all(by_card[i].status == "done" for i in (0, 1, 2, 4, 5))


def test_a_plain_pool_that_breaks_fails_the_rest_with_a_reason():
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("forkserver")) as pool:
        records = list(run_tasks(_crash_on_three, _tasks(6), pool, stage="test", param_hash="p", window=1))
    by_card = {r.card_id: r for r in records}
    assert set(by_card) == set(range(6))
    assert [by_card[i].status for i in range(6)] == ["done"] * 3 + ["failed"] * 3


@dataclass(frozen=True)
class _Params:
    ratio: float = 0.7
    nested: tuple[int, int] = (1, 2)


def test_param_hash_is_stable_and_sensitive():
    assert param_hash(_Params()) == param_hash(_Params())
    assert param_hash(_Params()) != param_hash(_Params(ratio=0.8))
    assert len(param_hash(_Params())) == 16


def test_stage_tasks_survive_the_trip_to_a_worker_process():
    """Process pools and dask pickle the task; a lambda or closure here would fail at run time."""
    import pickle

    from pipeline.filter import FilterParams
    from pipeline.stages.filter import filter_task

    task = functools.partial(filter_task, params=FilterParams(ratio=0.6))
    restored = pickle.loads(pickle.dumps(task))
    assert restored.func is filter_task and restored.keywords["params"] == FilterParams(ratio=0.6)
