"""The latency benchmark's synthetic frames and percentiles (`dimenet bench` itself: tests/cli/test_bench.py)."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime.bench.latency import bench_frames, percentiles_us
from dimenet.runtime.errors import InputError


def test_bench_frames_have_exactly_the_requested_points():
    p2, p3 = bench_frames(5, 100, (4032, 3024))
    assert p2.shape == (5, 100, 2) and p3.shape == (5, 100, 3)
    assert np.all(np.isfinite(p2)) and np.all(np.isfinite(p3))
    with pytest.raises(InputError, match="--points"):
        bench_frames(5, 1000, (4032, 3024))
    assert percentiles_us([1.0, 2.0, 3.0])["max"] == 3.0
