"""`dimenet bench --stream` times --temporal, with and without --motion, beside per frame (issue 51 step 5)."""

from __future__ import annotations

import json

import numpy as np

from dimenet.runtime.bench.streaming import FRAME_NS, bench_gyro
from dimenet.runtime.cli.main import main


def test_bench_gyro_spans_the_frames():
    g = bench_gyro(30)
    assert g.shape[1] == 4 and g[0, 0] == 0 and g[-1, 0] <= 30 * FRAME_NS and np.all(np.diff(g[:, 0]) > 0)


def test_stream_bench_times_the_temporal_modes(capsys):
    assert main(["bench", "--stream", "12", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    for name in ("temporal", "temporal_motion"):
        assert figures[f"{name}_s"] > 0 and np.isfinite(figures[f"{name}_extra_us_per_frame"])
