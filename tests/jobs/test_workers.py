"""A function over jobs shared by threads of this process and helper processes (``jobs.workers.run_shared``)."""

from __future__ import annotations

import math
import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor

import cv2
import pytest
from helpers import pid_slow_here

from dimenet.runtime.jobs.workers import LOCAL_THREADS, run_shared


def where_slow_here(seconds: float) -> tuple[int, str]:
    """(process id, thread name), after ``seconds`` of sleep in this process (``pid_slow_here``)."""
    return pid_slow_here(seconds), threading.current_thread().name


def test_two_workers_are_two_threads_of_this_process_and_results_come_in_the_jobs_order():
    assert LOCAL_THREADS == 2
    where = list(run_shared(where_slow_here, [0.05] * 8, 2))
    assert {pid for pid, _ in where} == {os.getpid()}
    assert len({name for _, name in where}) == 2  # both threads took jobs
    assert list(run_shared(math.sqrt, [k * k for k in range(20)], 2)) == [float(k) for k in range(20)]


def test_more_workers_add_helper_processes_that_join_when_up():
    pids = list(run_shared(pid_slow_here, [0.5] * 8, 3))  # 0.5 s a job here, none in a helper
    assert len(pids) == 8 and os.getpid() in pids and len(set(pids)) == 2
    assert pids[0] == os.getpid()  # this process starts at once, before any helper is up


def test_a_short_run_does_not_wait_for_helpers_coming_up_and_they_are_shut_down_after(monkeypatch):
    release = threading.Event()
    submit = ProcessPoolExecutor.submit

    def held_submit(self, *args, **kwargs):  # a helper that takes as long as the test wants to come up
        release.wait(60)
        return submit(self, *args, **kwargs)

    monkeypatch.setattr(ProcessPoolExecutor, "submit", held_submit)
    assert list(run_shared(math.sqrt, [4.0], 3)) == [2.0]  # returned while the helper is held back
    starter = [t for t in threading.enumerate() if t.name == "dimenet-helpers"]
    assert len(starter) == 1 and starter[0].is_alive()
    release.set()
    starter[0].join(timeout=60)
    assert not starter[0].is_alive() and not multiprocessing.active_children()


@pytest.mark.parametrize("workers", [2, 3])
def test_an_error_of_a_job_propagates_and_opencvs_threads_are_restored(workers):
    threads = cv2.getNumThreads()
    with pytest.raises(ValueError, match="math domain error"):
        list(run_shared(math.sqrt, [4.0, -1.0, 9.0], workers))
    assert cv2.getNumThreads() == threads
