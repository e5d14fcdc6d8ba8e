"""`dimenet bench --stream` times --temporal, with and without --motion (the gyroscope's, the lens shift's), beside
per frame (issue 51 step 5)."""

from __future__ import annotations

import json

import numpy as np

from dimenet.runtime.bench.streaming import FRAME_NS, bench_gyro, bench_lens_shift
from dimenet.runtime.cli.main import main


def test_the_bench_motions_span_the_frames():
    for g, columns in ((bench_gyro(30), 4), (bench_lens_shift(30), 3)):
        assert g.shape[1] == columns and g[0, 0] == 0 and g[-1, 0] <= 30 * FRAME_NS and np.all(np.diff(g[:, 0]) > 0)


def test_stream_bench_times_the_temporal_modes(capsys):
    assert main(["bench", "--stream", "12", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    for name in ("temporal", "temporal_motion", "temporal_lens_shift"):
        assert figures[f"{name}_s"] > 0 and np.isfinite(figures[f"{name}_extra_us_per_frame"])
