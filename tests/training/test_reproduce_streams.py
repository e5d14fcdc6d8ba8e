"""`dimenet reproduce`'s streams section (training/reproduce/streams.py): every stream method scored on each
recording, the plotted recording's K over time, the table and the plot in the report."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from dimenet.training.reproduce import streams
from dimenet.training.reproduce.report import STREAM_COLUMNS, STREAM_PLOT, _streams_report, plot_stream


def test_the_streams_are_scored_plotted_and_reported(monkeypatch):
    monkeypatch.setattr(streams, "RECORDINGS", (("natural", 0), ("rig", 0)))
    out = streams.run_streams(1.0)
    assert json.loads(json.dumps(out)) == out  # results.json takes it as it is
    assert set(out["rho"]) == {"natural 0", "rig 0"}
    assert set(STREAM_COLUMNS) <= set(out["rho"]["rig 0"]) and out["rho"]["rig 0"]["per_frame"] > 0.5
    plot = out["plot"]
    F = len(plot["t_s"])
    assert plot["name"] == "natural 0" and F > 10 and plot["t_s"][0] == 0.0
    assert np.shape(plot["k_true"]) == np.shape(plot["k_platform"]) == (F, 4) and len(plot["k_c"]) == 4
    assert {"per_frame", "temporal", "gyro", "lens_shift"} <= set(plot["methods"])
    assert all(np.shape(m["k"]) == np.shape(m["sigma"]) == (F, 4) for m in plot["methods"].values())
    text = "\n".join(_streams_report(out))
    assert "| recording | " + " | ".join(STREAM_COLUMNS) + " |" in text
    assert "| rig 0 | " in text and f"({STREAM_PLOT})" in text
    png = plot_stream(plot)
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
