"""Run a per-card task over many cards through any ``concurrent.futures.Executor``.

The executor is a seam: a local process pool or a dask cluster's executor
(``dask.distributed.Client.get_executor()``). Tasks are submitted through a bounded window that
follows the executor's capacity (:func:`in_flight_window`), so a 250,000-card run holds a few
futures per worker thread, never one per card, and results are yielded as they complete for
the driver to write in batches.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from . import CODE_VERSION
from .io import STALE_TEMP_SECONDS, remove_stale_temp_files
from .records import CardTask, StageRecord

TaskFunction = Callable[[CardTask], StageRecord]


# Thread-count variables read by BLAS/OpenMP libraries when they load (scipy's own OpenBLAS
# loads lazily, after a worker starts).
ONE_THREAD_ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def init_worker() -> None:
    """Worker initializer: one thread per worker for OpenCV and the BLAS libraries (we
    parallelise by card), and freed memory kept for the next card (:func:`keep_freed_memory`).

    A worker beside one per core gains nothing from inner threads, and OpenBLAS's idle threads
    spin after every call: CPU charged to the card. OpenCV's wheel bundles its own OpenBLAS for
    ``cv2.gemm`` (the filter's 2,000 x 2,000 descriptor product), which ``cv2.setNumThreads``
    does not reach; numpy's serves the small ``lstsq`` of every stage. Libraries already loaded
    are limited through threadpoolctl; the environment covers those loaded later (scipy's own
    OpenBLAS). Measured with ``keystone bench pipeline --variant work`` run alternately with the
    code before, CPU-s a card at 760 / 1400 / ~3000 px: one BLAS thread 0.425 / 0.917 / 1.285 ->
    0.372 / 0.849 / 1.212; both settings 0.429 / 0.892 / 1.245 -> 0.347 / 0.711 / 1.027
    (docs/BENCHMARKS.md, "A worker's threads and memory"). Dask workers get this through
    :class:`pipeline.dask_worker.OneThreadWorkerPlugin`."""
    import os

    os.environ.update(ONE_THREAD_ENVIRONMENT)
    import cv2
    from threadpoolctl import threadpool_limits  # type: ignore[import-untyped]

    cv2.setNumThreads(1)
    threadpool_limits(limits=1)
    keep_freed_memory()


# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
# bytes: the largest mmap threshold glibc accepts on 64-bit (4 * 1024 * 1024 * sizeof(long)).
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024


def keep_freed_memory(trim_threshold: int = 256 * 1024 * 1024, top_pad: int = 64 * 1024 * 1024) -> bool:
    """Let glibc keep the memory a card frees for the next card instead of handing it back.

    A card allocates and frees the same few image-sized arrays (up to ~14 MB for a 3000 px
    scan) in every stage. By default glibc maps blocks over its dynamic threshold afresh each
    time and returns the heap's free top once it passes twice that threshold, so the kernel
    zeroes the same pages again and again: system CPU charged to the card. Here arrays up to
    ``_MMAP_THRESHOLD_MAX`` come from the heap and up to ``trim_threshold`` bytes of free top
    stay mapped (a worker's peak memory does not grow: what it keeps it had just used).
    Returns whether the settings took (False off glibc, e.g. macOS or musl)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return all(
        mallopt(option, value) == 1
        for option, value in (
            (_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX),
            (_M_TRIM_THRESHOLD, trim_threshold),
            (_M_TOP_PAD, top_pad),
        )
    )


class RestartingProcessPool(Executor):
    """A process pool that replaces itself when a worker dies, so the rest of a batch goes on.

    A dead worker breaks a ``ProcessPoolExecutor`` for good: every pending future fails with
    ``BrokenProcessPool`` and every later ``submit`` raises. Here the futures in flight still
    fail (the driver records them as ``worker_crashed`` and a rerun retries them), but the next
    submit gets a fresh pool. ``forkserver`` workers start clean of the parent's threads.
    """

    def __init__(self, max_workers: int) -> None:
        self._max_workers = max_workers
        self._context = multiprocessing.get_context("forkserver")
        self._pool = self._new_pool()
        self.restarts = 0

    @property
    def max_workers(self) -> int:
        """Worker processes, one card at a time each."""
        return self._max_workers

    def _new_pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(self._max_workers, mp_context=self._context, initializer=init_worker)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        try:
            return self._pool.submit(fn, *args, **kwargs)
        except BrokenProcessPool:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._new_pool()
            self.restarts += 1
            return self._pool.submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)


# Cards in flight per worker thread. Two: the card a thread computes and the next one, already
# sent, so a thread that finishes starts again without waiting for the driver. The driver is
# away from the executor while it writes a batch of results (runs.loop: 50 records or 2 s; its
# whole cost is 1.5-2.8 ms of CPU a record in `keystone bench driver`, so ~0.1 s a batch) or
# claims the next cards; a card costs 0.3-1 CPU-s, so one card ready per thread covers that
# pause several times over, and eight a thread ran no faster than two (docs/SCALE.md). It is also what a dask scheduler hands a
# single-threaded worker on its own (worker-saturation 1.1: ceil(1.1 x 1) = 2 tasks), so a
# larger window would only queue futures at the scheduler: cards claimed but not started, that
# another run cannot take and that a dead driver leaves held until the claims lapse. The window
# grows with the threads, never with the cards: a 250,000-card run holds as many futures as a
# 25-card one.
WINDOW_PER_THREAD = 2


def in_flight_window(worker_threads: int, per_thread: int = WINDOW_PER_THREAD) -> int:
    """How many cards to keep in flight for an executor with ``worker_threads`` threads that
    compute cards (``per_thread`` each, :data:`WINDOW_PER_THREAD`). A cluster with no worker
    yet still gets ``per_thread`` cards, which wait at its scheduler for the first worker."""
    if per_thread < 1:
        raise ValueError(f"per_thread must be at least 1, got {per_thread}")
    return max(1, worker_threads) * per_thread


@dataclass
class InFlight:
    """What :func:`run_tasks` did with its window, for the run's report and the driver bench:
    the window it last used, the most cards it held in flight at once, how many it submitted,
    and when it submitted the first and the last (``time.perf_counter``)."""

    window: int = 0
    most: int = 0
    submitted: int = 0
    first_submit: float = 0.0
    last_submit: float = 0.0


# Seconds a run waits on its cards in flight before it looks at a window that can change (a
# dask cluster's workers joining) again.
WINDOW_RECHECK_S = 2.0


def run_tasks(
    function: TaskFunction,
    tasks: Iterable[CardTask],
    executor: Executor | None = None,
    *,
    stage: str,
    param_hash: str,
    window: int | Callable[[], int] = WINDOW_PER_THREAD,
    flight: InFlight | None = None,
) -> Iterator[StageRecord]:
    """Yield one :class:`StageRecord` per task, in completion order.

    With no executor the tasks run inline (one core, easiest to debug). Otherwise at most
    ``window`` cards are in flight: a number, or a function giving it, asked again before each
    refill and at least every :data:`WINDOW_RECHECK_S` while the run waits (it must be cheap:
    ``runs.executors.dispatch_window`` reads a dask cluster's threads at most that often). The
    default suits a single worker; a driver sizes it with :func:`in_flight_window`. ``flight``,
    when given, is filled in as the run goes.

    A worker that dies (a segfault in native code, the OOM killer) fails only its in-flight
    cards, recorded with reason ``worker_crashed``; the caller may rerun them.
    """
    if executor is None:
        for inline_task in tasks:
            clear_stale_temp_files(inline_task)
            yield function(inline_task)
        return

    flight = flight if flight is not None else InFlight()
    pending: dict[Future[StageRecord], CardTask] = {}
    source = iter(tasks)
    exhausted = False
    while True:
        flight.window = window() if callable(window) else window
        while not exhausted and len(pending) < flight.window:
            task = next(source, None)
            if task is None:
                exhausted = True
                break
            clear_stale_temp_files(task)
            try:
                pending[executor.submit(function, task)] = task
            except BrokenProcessPool:
                yield _crashed(task, stage, param_hash)
                continue
            flight.last_submit = time.perf_counter()
            if not flight.submitted:
                flight.first_submit = flight.last_submit
            flight.submitted += 1
        flight.most = max(flight.most, len(pending))
        if not pending:
            return
        recheck = WINDOW_RECHECK_S if callable(window) and not exhausted else None
        done, _ = wait(pending, timeout=recheck, return_when=FIRST_COMPLETED)
        for future in done:
            task = pending.pop(future)
            try:
                yield future.result()
            except BrokenProcessPool:
                yield _crashed(task, stage, param_hash)
            except Exception as exc:  # the function itself catches card errors; this is transport
                yield StageRecord(
                    card_id=task.card_id,
                    stage=stage,
                    param_hash=param_hash,
                    status="failed",
                    reason=f"executor_error: {type(exc).__name__}: {exc}",
                    started_at=time.time(),
                    code_version=CODE_VERSION,
                )


def clear_stale_temp_files(task: CardTask) -> None:
    """Remove what a killed run left in this card's work folder (half-written ``.tmp`` files of
    :func:`~pipeline.io.atomic_write`) before the card runs again. Per card, not a walk of the
    whole data dir: only cards in flight when a run died can hold them, and those are exactly the
    ones run again; a walk of 500,000 artifacts took 26-110 s on a loaded machine."""
    if task.work_dir:
        remove_stale_temp_files(task.work_dir, STALE_TEMP_SECONDS)


def _crashed(task: CardTask, stage: str, param_hash: str) -> StageRecord:
    return StageRecord(
        card_id=task.card_id,
        stage=stage,
        param_hash=param_hash,
        status="failed",
        reason="worker_crashed: the worker process died while handling this card; rerun to retry",
        started_at=time.time(),
        code_version=CODE_VERSION,
    )
