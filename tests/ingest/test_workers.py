"""Jobs shared by this process and helper processes (``workers.run_shared``)."""

from __future__ import annotations

import math
import os

import cv2
import pytest
from helpers import pid_slow_here

from dimenet.runtime.ingest.workers import run_shared


def test_results_come_in_the_jobs_order_from_this_process_and_a_helper():
    pids = list(run_shared(pid_slow_here, [[0.5]] * 8, 2))  # here 0.5 s a job, in a helper at once
    assert len(pids) == 8 and os.getpid() in pids and len(set(pids)) == 2
    assert pids[0] == os.getpid()  # this process starts at once, before any helper is up
    assert list(run_shared(math.sqrt, [[k * k] for k in range(20)], 2)) == [float(k) for k in range(20)]


def test_an_error_of_a_job_propagates_and_opencvs_threads_are_restored():
    threads = cv2.getNumThreads()
    with pytest.raises(ValueError, match="math domain error"):
        list(run_shared(math.sqrt, [[4.0], [-1.0], [9.0]], 2))
    assert cv2.getNumThreads() == threads
