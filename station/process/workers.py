"""Per-frame work spread over worker processes: developing and matting a shot is single-threaded
numpy and OpenCV, so a scan's 240 shots use one core unless each worker takes its own. Reading and
rewriting image files needs only threads: the codecs release the GIL."""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import threading
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from typing import Callable, Iterable, TypeVar

Job = TypeVar("Job")
Result = TypeVar("Result")
Context = TypeVar("Context")


def available_cores() -> int:
    """The cores this process may use: its CPU affinity, capped by OMP_NUM_THREADS when that is set (the test
    runner's workers and the batch runner's stage processes each keep to their share this way)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    limit = os.environ.get("OMP_NUM_THREADS", "")
    return max(1, min(cores, int(limit))) if limit.isdigit() and int(limit) > 0 else max(1, cores)


def map_in_workers(
    work: Callable[[Job], Result], jobs: Iterable[Job], context: Context,
    set_context: Callable[[Context], None], workers: int = 0,
) -> list[Result]:
    """`work` over `jobs`, results in order, in `workers` processes (0: `available_cores()`), each given `context` once
    through `set_context`. One worker, or one job, runs here in this process.

    Workers are spawned, not forked: a fork of a process whose torch or OpenMP pool is running can hang.
    A worker's exception is raised here, from the job that failed.
    """
    jobs = list(jobs)
    count = min(workers or available_cores(), len(jobs))
    if count <= 1:
        set_context(context)
        return [work(job) for job in jobs]
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(count, mp_context=spawn, initializer=_start_worker, initargs=(set_context, context)) as pool:
        return list(pool.map(work, jobs, chunksize=max(1, len(jobs) // (8 * count))))


def map_in_threads(work: Callable[[Job], Result], jobs: Iterable[Job]) -> list[Result]:
    """`work` over `jobs`, results in order, on one thread per available core; for work that spends its time
    in codecs (PNG, EXR) that release the GIL. An exception is raised here, from the job that failed."""
    jobs = list(jobs)
    count = min(available_cores(), len(jobs))
    if count <= 1:
        return [work(job) for job in jobs]
    with ThreadPoolExecutor(count) as pool:
        return list(pool.map(work, jobs))


def _start_worker(set_context: Callable[[Context], None], context: Context) -> None:
    """One thread per worker: the workers together take the cores."""
    import cv2

    threading.Thread(target=_exit_with_parent, daemon=True).start()
    cv2.setNumThreads(1)
    set_context(context)


def _exit_with_parent() -> None:
    """A worker outlives a parent that is killed or exits at once (a fenced batch stage): it waits on the
    job queue, whose write end it holds itself, and keeps the parent's stdout open. Leave with the parent."""
    multiprocessing.connection.wait([multiprocessing.parent_process().sentinel])
    os._exit(1)
