"""A function over items (jobs) worked on by threads of this process and by helper processes at once, the results in
the items' order (ingest's photos: ``ingest.pipeline``).

``run_shared`` with N workers: LOCAL_THREADS (2) threads of this process, or N when fewer, take the next job whenever
they are free, from the start; with more workers, N − 2 helper processes (a ``concurrent.futures`` process pool
started from a fork server that has imported the function's module, or spawned where the platform has no fork server)
join as they come up. Threads start at once but share Python's lock: OpenCV, most of a photo's work, lets go of it
while it runs, so two threads keep two cores busy, but the photo's Python part runs on one core at a time, so more
threads would add little. A helper process costs a fraction of a second of a core before its first job (the fork
server's imports of numpy, OpenCV and the function's module), most of a run of a handful of photos (the figures:
models_spec/ingest.md, "Measured"). OpenCV runs on one thread in each worker (in this process
while it works).

This process does not wait for helpers still coming up when every job is done: the thread that started them shuts
the pool down once they are up (the interpreter waits for it at exit).
"""

from __future__ import annotations

import multiprocessing
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, Callable

import cv2

LOCAL_THREADS = 2  # threads of this process that work on jobs (fewer when there are fewer workers)


def worker_context(preload: str) -> multiprocessing.context.BaseContext:
    """How helper processes start: from a fork server that has imported the module ``preload`` (no OpenCV thread
    forked; POSIX), else spawned (each importing it on its first job)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([preload])
    return context


def _ready() -> None:
    """A helper's first call: it has started."""


def run_shared(fn: Callable[[Any], Any], jobs: Sequence[Any], workers: int) -> Iterator[Any]:
    """``fn(job)`` for every job, yielded in the jobs' order, by ``workers`` workers: threads of this process and
    helper processes (see the module doc); ``fn`` must be thread-safe, and with helpers ``fn`` and the jobs picklable
    (the fork server imports ``fn``'s module). An exception of ``fn`` propagates (the jobs not yet started are
    dropped)."""
    n = len(jobs)
    cond = threading.Condition()
    state = {"taken": 0, "stopping": False, "starting": True, "closed": False}
    results: dict[int, tuple[bool, Any]] = {}  # job index -> (done without error, its result or exception)

    def take() -> int:
        """The next job's index, or -1 when none is left."""
        with cond:
            if state["stopping"] or state["taken"] >= n:
                return -1
            state["taken"] += 1
            return state["taken"] - 1

    def put(i: int, ok: bool, value: Any) -> None:
        with cond:
            results[i] = (ok, value)
            state["stopping"] |= not ok
            cond.notify_all()

    def work() -> None:  # a thread of this process
        while (i := take()) >= 0:
            try:
                put(i, True, fn(jobs[i]))
            except Exception as exc:
                put(i, False, exc)

    def next_job(pool: ProcessPoolExecutor) -> None:  # a helper is free: it gets the next job
        i = take()
        if i < 0:
            return
        try:
            pool.submit(fn, jobs[i]).add_done_callback(lambda done: finished(pool, i, done))
        except Exception as exc:  # a broken pool: the job's result is that error
            put(i, False, exc)

    def finished(pool: ProcessPoolExecutor, i: int, done: Future) -> None:  # a helper's job is done
        if done.cancelled():  # the pool is shut down
            return
        exc = done.exception()
        put(i, exc is None, exc if exc is not None else done.result())
        next_job(pool)

    def came_up(pool: ProcessPoolExecutor, up: Future) -> None:  # a helper has started, or could not
        if not up.cancelled() and up.exception() is None:  # else the threads do its share
            next_job(pool)

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    helpers = workers - min(workers, LOCAL_THREADS)
    pool = None
    if helpers:
        pool = ProcessPoolExecutor(
            helpers, mp_context=worker_context(fn.__module__), initializer=cv2.setNumThreads, initargs=(1,)
        )

    def start() -> None:  # the first submit starts the helpers, and waits for the fork server's imports
        try:
            for _ in range(helpers):
                pool.submit(_ready).add_done_callback(lambda up: came_up(pool, up))
        except (RuntimeError, OSError):  # a broken pool, or no process could start: the threads do every job
            pass
        with cond:
            state["starting"] = False
            closed = state["closed"]
        if closed:  # the jobs were over before the helpers were up
            pool.shutdown(cancel_futures=True)

    if pool is not None:
        threading.Thread(target=start, name="dimenet-helpers").start()
    team = [threading.Thread(target=work, name=f"dimenet-worker-{k}", daemon=True) for k in range(workers - helpers)]
    for t in team:
        t.start()
    try:
        for k in range(n):
            with cond:
                cond.wait_for(lambda: k in results)  # noqa: B023 (waited for here, at once)
                ok, value = results.pop(k)
            if not ok:
                raise value
            yield value
    finally:
        with cond:
            state["stopping"] = state["closed"] = True
            starting = state["starting"]
        for t in team:
            t.join()
        cv2.setNumThreads(threads)
        if pool is not None and not starting:  # else the starter shuts the pool down once the helpers are up
            pool.shutdown(cancel_futures=True)
