"""bench.streams: the methods side by side on a recording, rho over settled frames on held-out points."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime.bench.streams import METHODS, SETTLE, _masks, score_recording
from dimenet.runtime.sim.recording import simulate_recording


@pytest.fixture(scope="module")
def recording():
    return simulate_recording(2, seconds=3.0, cuts=1)


def test_settled_frames_skip_the_start_and_each_event(recording):
    settled, after = _masks(recording)
    assert not settled[:SETTLE].any()
    for event in (*recording.cuts, *recording.refocus):
        assert not settled[event : event + SETTLE].any() and after[event + 5 : event + 10].all()


def test_scores_every_method(recording):
    s = score_recording(recording)
    platform = ("platform_prior", "platform_temporal")
    assert set(s.rho) == {"platform", *platform, *METHODS} and s.frames == recording.dataset.n_frames
    for name in (*METHODS, *platform):
        assert s.rho[name] is None or np.isfinite(s.rho[name])
        assert 0.0 <= s.coverage[name] <= 1.0 and 0.0 <= s.own_k[name] <= 1.0
    assert s.rho["gyro"] is not None and s.rho["gyro"] > s.rho["per_frame"]
