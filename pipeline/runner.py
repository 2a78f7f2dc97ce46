"""Run a per-card task over many cards through any ``concurrent.futures.Executor``.

The executor is a seam: a local process pool today, a distributed engine's executor (e.g.
``dask.distributed.Client.get_executor()``) tomorrow. Tasks are submitted through a bounded
window so a 250,000-card run holds only a few futures at a time, and results are yielded as
they complete for the driver to write in batches.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
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


def run_tasks(
    function: TaskFunction,
    tasks: Iterable[CardTask],
    executor: Executor | None = None,
    *,
    stage: str,
    param_hash: str,
    window: int = 16,
) -> Iterator[StageRecord]:
    """Yield one :class:`StageRecord` per task, in completion order.

    With no executor the tasks run inline (one core, easiest to debug). A worker that dies
    (a segfault in native code, the OOM killer) fails only its in-flight cards, recorded with
    reason ``worker_crashed``; the caller may rerun them.
    """
    if executor is None:
        for inline_task in tasks:
            clear_stale_temp_files(inline_task)
            yield function(inline_task)
        return

    pending: dict[Future[StageRecord], CardTask] = {}
    source = iter(tasks)
    exhausted = False
    while True:
        while not exhausted and len(pending) < window:
            task = next(source, None)
            if task is None:
                exhausted = True
                break
            clear_stale_temp_files(task)
            try:
                pending[executor.submit(function, task)] = task
            except BrokenProcessPool:
                yield _crashed(task, stage, param_hash)
        if not pending:
            return
        done, _ = wait(pending, return_when=FIRST_COMPLETED)
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
