"""Jobs worked on by this process and helper processes at once, the results in the jobs' order.

``run_shared`` with N workers: this process and N − 1 helper processes (a ``concurrent.futures`` process pool
started from a fork server that has imported the pipeline, or spawned where the platform has no fork
server) take the next job whenever they are free; OpenCV runs on one thread in each (in this one while
it works). A helper is handed its first job only once it has started, so no job waits for a helper's
start-up (0.3-0.6 s for the fork server to import numpy, OpenCV and the pipeline) while this process
could run it: a handful of photos is done by the time a pool alone would have begun.
"""

from __future__ import annotations

import multiprocessing
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Callable

import cv2

PRELOAD = "dimenet.runtime.ingest.pipeline"  # what the fork server imports before it forks a helper


def worker_context() -> multiprocessing.context.BaseContext:
    """How helper processes start: from a fork server that has imported PRELOAD (no OpenCV thread forked;
    POSIX), else spawned (each importing it on its first job)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([PRELOAD])
    return context


def _ready() -> None:
    """A helper's first call: it has started."""


def run_shared(fn: Callable[..., Any], jobs: Sequence[Sequence[Any]], workers: int) -> Iterator[Any]:
    """``fn(*job)`` for every job, yielded in the jobs' order, by this process and ``workers`` − 1 helpers (see
    the module doc); ``fn`` and the jobs must be picklable. An exception of ``fn`` propagates (the jobs not yet
    started are dropped)."""
    n = len(jobs)
    lock = threading.Lock()
    state = {"taken": 0, "stopping": False}
    handed: dict[int, Future] = {}
    local: dict[int, Any] = {}

    def take() -> int:
        """The next job's index (under the lock), or -1 when none is left."""
        if state["stopping"] or state["taken"] >= n:
            return -1
        state["taken"] += 1
        return state["taken"] - 1

    def hand(pool: ProcessPoolExecutor, _done: Future) -> None:  # a helper is free: it gets the next job
        with lock:
            i = take()
            if i < 0:
                return
            try:
                handed[i] = pool.submit(fn, *jobs[i])
            except Exception as exc:  # a broken pool: the job's result is that error
                handed[i] = Future()
                handed[i].set_exception(exc)
                return
        handed[i].add_done_callback(lambda done: hand(pool, done))

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    pool = ProcessPoolExecutor(workers - 1, mp_context=worker_context(), initializer=cv2.setNumThreads, initargs=(1,))

    def start() -> None:  # the first submit starts the helpers, and waits for the fork server's imports
        for _ in range(workers - 1):
            try:
                pool.submit(_ready).add_done_callback(lambda done: hand(pool, done))
            except Exception:  # the pool is shut down already (this process did every job) or broken
                return

    starter = threading.Thread(target=start, name="dimenet-helpers", daemon=True)
    starter.start()
    try:
        out = 0
        while True:
            while out in local or (out in handed and handed[out].done()):
                yield local.pop(out) if out in local else handed.pop(out).result()
                out += 1
            with lock:
                i = take()
            if i < 0:
                break
            local[i] = fn(*jobs[i])
        for k in range(out, n):  # every job is taken: each is here or with a helper
            yield local.pop(k) if k in local else handed.pop(k).result()
    finally:
        with lock:
            state["stopping"] = True
        starter.join()
        pool.shutdown(cancel_futures=True)
        cv2.setNumThreads(threads)
