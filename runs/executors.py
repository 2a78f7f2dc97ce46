"""The executors a run computes on: inline, a restarting process pool, or a dask cluster."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from contextlib import contextmanager
from typing import Any

from pipeline.runner import WINDOW_RECHECK_S, RestartingProcessPool, in_flight_window, init_worker


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


def _dask_client(executor: Executor) -> Any | None:
    """The client behind a dask ``Client.get_executor()`` (distributed's ClientExecutor keeps it
    as ``_client``), or None for any other executor; dask is not imported for the check."""
    if type(executor).__module__.split(".")[0] != "distributed":
        return None
    return getattr(executor, "_client", None)


def worker_threads(executor: Executor | None) -> int:
    """Threads that compute cards at once: 1 inline, a process or thread pool's workers, a dask
    cluster's threads (every worker's ``nthreads`` summed, as its scheduler counts them now: one
    round trip)."""
    if executor is None:
        return 1
    client = _dask_client(executor)
    if client is not None:
        return sum(client.nthreads().values())
    if isinstance(executor, RestartingProcessPool):
        return executor.max_workers
    workers = getattr(executor, "_max_workers", None)  # concurrent.futures' own pools
    if isinstance(workers, int):
        return workers
    raise TypeError(f"cannot tell how many workers {type(executor).__name__} has; give run_tasks a window")


def dispatch_window(executor: Executor | None, recheck_s: float = WINDOW_RECHECK_S) -> int | Callable[[], int]:
    """The in-flight window of a run on ``executor`` (:func:`pipeline.runner.in_flight_window`
    of its :func:`worker_threads`). A pool's is a number; a dask cluster's is a function that
    asks the scheduler again at most every ``recheck_s`` seconds, so workers that join a
    running cluster get cards (and the window shrinks when workers leave)."""
    client = None if executor is None else _dask_client(executor)
    if client is None:
        return in_flight_window(worker_threads(executor))
    state = {"window": in_flight_window(worker_threads(executor)), "read_at": time.monotonic()}

    def window() -> int:
        now = time.monotonic()
        if now - state["read_at"] >= recheck_s:
            state["window"], state["read_at"] = in_flight_window(worker_threads(executor)), now
        return int(state["window"])

    return window
