"""The engine (``jobs.engine``): one function over items, each item's outcome in the items' order, here or as
Ray jobs in one session (fleet's use of it: tests/training/test_fleet.py)."""

from __future__ import annotations

import math

import pytest

from dimenet.runtime.jobs.engine import Engine, EngineError, run_all


def _double(x):
    if x == 3:
        raise ValueError("three")
    return 2 * x


def test_the_engine_keeps_order_and_turns_a_failure_into_its_outcome():
    outcomes = run_all(_double, [1, 2, 3, 4])
    assert [o.value for o in outcomes] == [2, 4, None, 8] and "ValueError: three" in outcomes[2].error
    with pytest.raises(EngineError, match="local:N needs N >= 1"):
        pytest.importorskip("ray")
        run_all(_double, [1], address="local:0")


def test_one_engine_session_serves_dependent_batches(capfd):
    ray = pytest.importorskip("ray")
    with Engine("local:2") as engine:  # the jobs: a function Ray's workers can import
        first = engine.run_all(math.sqrt, [16.0, 81.0])
        assert ray.is_initialized()
        second = engine.run_all(math.sqrt, [o.value for o in first] + [-1.0])
    assert not ray.is_initialized()
    assert [o.value for o in second] == [2.0, 3.0, None] and "ValueError: math domain error" in second[2].error
    # Ray's notice that it turned token authentication on, on every local cluster it starts, is not ours to print
    assert "Token authentication is enabled" not in capfd.readouterr().err
