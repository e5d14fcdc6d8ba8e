"""Rectifier in mode map: the posterior K_cov, the need for an uncertainty model, the spec round trip."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from helpers import constant_uncertainty, model_spec, random_model_file

from dimenet.runtime.errors import InputError, ModelError
from dimenet.runtime.rectify import checks
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.uncertainty import Uncertainty


def test_rectifier_map_mode_fits_at_least_as_well_and_reports_its_posterior(map_model):
    frames, path = map_model
    dimenet, fused = Rectifier.load(path), Rectifier.load(path, mode="map")
    rig = np.flatnonzero(frames.scene == "rig")[-4:]
    for b in rig:
        m = frames.valid[b]
        a, c = (
            dimenet.rectify(frames.points_2d[b][m], frames.points_3d[b][m]),
            fused.rectify(frames.points_2d[b][m], frames.points_3d[b][m]),
        )
        if a.fallback is None:
            np.testing.assert_allclose(a.K_cov, np.eye(4) * 64.0)
        assert c.fallback is None and "map" in c.timings_us
        assert c.reprojection_error_px <= a.reprojection_error_px + 1e-9
        assert np.all(np.linalg.eigvalsh(c.K_cov) > 0) and np.all(np.diag(c.K_cov) < 64.0)
    batch = fused.rectify_batch(frames.points_2d[rig], frames.points_3d[rig], frames.valid[rig])
    one = [fused.rectify(frames.points_2d[b][frames.valid[b]], frames.points_3d[b][frames.valid[b]]) for b in rig]
    np.testing.assert_allclose(batch.K, [o.K for o in one], atol=1e-6)
    np.testing.assert_allclose(batch.K_cov, [o.K_cov for o in one], rtol=1e-6)


def test_batch_covariance_is_the_single_frame_covariance_of_the_inference_points(
    tmp_path, map_model, monkeypatch, without_evidence_rule
):
    frames, _ = map_model
    # The random network's K may fit a frame worse than K_c (then no K_cov): the worse and evidence rules are off
    # here, as
    # the frames' errors come from other points in the batch (all valid) than in the single frames (inference).
    monkeypatch.setattr(checks, "worse", lambda e, e_c: np.zeros(np.shape(e), bool))
    coef = np.array([[1.0, -0.3, 0.2, 0.5, 0.1]] * 4) * [[1.0], [1.1], [0.9], [1.2]]  # every statistic counts
    spec = replace(model_spec(frames), uncertainty=Uncertainty(coef=coef, correlation=np.eye(4)))
    rectifier = Rectifier.load(random_model_file(tmp_path / "stats.onnx", spec))
    for scene, infer in (("rig", frames.valid), ("natural", frames.infer_mask)):
        idx = np.flatnonzero(frames.scene == scene)[:3]
        batch = rectifier.rectify_batch(
            frames.points_2d[idx], frames.points_3d[idx], frames.valid[idx], infer_mask=infer[idx]
        )
        # K_cov depends on the inference points only: one frame of just those gives the same.
        one = [rectifier.rectify(frames.points_2d[b][infer[b]], frames.points_3d[b][infer[b]]) for b in idx]
        assert all(o.fallback is None for o in one) and not any(batch.fallback)
        np.testing.assert_allclose(batch.K_cov, [o.K_cov for o in one], rtol=1e-9)


def test_map_mode_needs_an_uncertainty_model(tmp_path, map_model):
    frames, _ = map_model
    old = random_model_file(tmp_path / "old.onnx", model_spec(frames))
    assert (
        Rectifier.load(old).rectify(*(a[0][frames.valid[0]] for a in (frames.points_2d, frames.points_3d))).K_cov
        is None
    )
    with pytest.raises(ModelError, match=r"old\.onnx.*no uncertainty model.*'map'"):
        Rectifier.load(old, mode="map")
    with pytest.raises(InputError, match="mode must be one of dimenet, map"):
        Rectifier.load(old, mode="fast")


def test_spec_round_trips_its_uncertainty_and_still_reads_1_0(map_model):
    frames, _ = map_model
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(3.0))
    back = ModelSpec.from_json(spec.to_json())
    np.testing.assert_array_equal(back.uncertainty.coef, spec.uncertainty.coef)
    old = json.loads(model_spec(frames).to_json())
    old["version"] = "1.0.0"
    assert ModelSpec.from_dict(old).uncertainty is None
    correlated = replace(
        spec, uncertainty=replace(spec.uncertainty, data_correlation=np.array([0, 0, 0.7, 0.5]), noise_scale_px=1.5)
    )
    back = ModelSpec.from_json(correlated.to_json()).uncertainty
    np.testing.assert_array_equal(back.data_correlation, [0, 0, 0.7, 0.5])
    assert back.noise_scale_px == 1.5
    v12 = json.loads(spec.to_json())  # spec 1.2: no data correlation, the posterior is not widened
    v12["version"] = "1.2.0"
    del v12["uncertainty"]["data_correlation"], v12["uncertainty"]["noise_scale_px"]
    np.testing.assert_array_equal(ModelSpec.from_dict(v12).uncertainty.data_correlation, np.zeros(4))
