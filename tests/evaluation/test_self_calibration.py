"""The self-calibration baseline: per-frame K* fits and their fallbacks on planar frames and too few points."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from helpers import K_TEST

from dimenet.runtime.evaluation.self_calibration import self_calibrate
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.sim.simulator import simulate


def test_self_calibration_falls_back_on_planar_and_too_few_points():
    frames = simulate("galaxy-s8", seed=3, planar_frames=3)
    test = frames.select(frames.frames_in("test"))
    K_c = k_matrix(k_params(K_TEST))
    infer = test.infer_mask.copy()
    infer[0] = False
    infer[0, np.flatnonzero(test.valid[0])[:5]] = True
    result = self_calibrate(replace(test, infer_mask=infer), K_c)
    assert "5 inference points" in result.fallback[0] and np.all(result.K[0] == K_c)
    planar = np.flatnonzero(test.scene == "planar")
    assert all("ill-posed" in result.fallback[f] and "coplanar" in result.fallback[f] for f in planar)
    assert np.all(result.K[planar] == K_c)
    rig = np.flatnonzero(test.scene == "rig")[1:]
    assert all(result.fallback[f] is None for f in rig)
    assert np.abs(k_params(result.K[rig]) - k_params(test.K_true[rig])).mean() < 2.0
