"""Stage pnp_k's pose under K: Gauss-Newton steps from the C0 pose (``stages.pose_under``), and SQPnP's pose
under K tried before a rule refuses K at the steps' (``check_stage.frame_check``, ``check_stage.batch_errors``): a frame
refused with the steps is refused with SQPnP alone, and every K that stands with SQPnP alone stands with them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import constant_uncertainty, model_spec
from test_rectifier_camera import linear_model, rig_frames

from dimenet.runtime import native
from dimenet.runtime.geometry import k_matrix
from dimenet.runtime.geometry import solve_pnp_start as pnp
from dimenet.runtime.rectify import stages
from dimenet.runtime.rectify.rectifier import Rectifier


@pytest.fixture(scope="module")
def rig(frames):
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(3.0))
    p2, p3, valid = rig_frames(frames)
    noisy = p2 + np.random.default_rng(1).normal(0.0, 1.5, p2.shape)  # e_c ~2 px: K's move is near its noise
    return spec, np.clip(noisy, 0.0, np.array(spec.image_size) - 1.0), p3, valid


def sqpnp_only(p2, p3, k, delta_k, c0_pose):
    """``stages.pose_under`` as it was: SQPnP under K (the C0 pose where Delta K = 0)."""
    if not np.count_nonzero(delta_k):
        return c0_pose[0].copy(), c0_pose[1].copy(), None, False
    return (*pnp(p2, p3, k_matrix(k)), None, False)


def results(rect, p2, p3, valid):
    single = [rect.rectify(p2[b][valid[b]], p3[b][valid[b]]) for b in range(len(p2))]
    return single, rect.rectify_batch(p2, p3, valid)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_k_standing_with_sqpnp_alone_stands_and_none_fits_worse(rig, seed, monkeypatch, without_evidence_rule):
    spec, p2, p3, valid = rig
    rect = Rectifier(linear_model(spec, seed=seed, scale=0.005))
    stepped, stepped_batch = results(rect, p2, p3, valid)
    with monkeypatch.context() as m:
        m.setattr(stages, "pose_under", sqpnp_only)
        alone, _ = results(rect, p2, p3, valid)
    assert sum(r.fallback is None for r in alone) >= 3
    for s, a in zip(stepped, alone):
        assert a.fallback is not None or s.fallback is None
        assert s.reprojection_error_px <= s.reprojection_error_kc_px
        if s.fallback is None and a.fallback is None:  # the same K; the two poses a short step apart
            np.testing.assert_array_equal(s.K, a.K)
            np.testing.assert_allclose(s.rvec, a.rvec, atol=1e-3)
            assert abs(s.reprojection_error_px - a.reprojection_error_px) < 0.05 * a.reprojection_error_kc_px
    assert stepped_batch.fallback == tuple(s.fallback for s in stepped)
    np.testing.assert_allclose(stepped_batch.rvec, [s.rvec for s in stepped], atol=1e-9)


def test_a_k_refused_at_the_steps_pose_is_judged_again_at_sqpnp_s(rig, monkeypatch, without_evidence_rule):
    """Steps that land far off (the start pose 5 % further away) leave every K refused by the worse rule; SQPnP's
    pose is then tried, and each frame ends as it does with SQPnP alone, one by one and in a batch."""
    spec, p2, p3, valid = rig
    rect = Rectifier(linear_model(spec, scale=0.005))
    with monkeypatch.context() as m:
        m.setattr(stages, "pose_under", sqpnp_only)
        alone, alone_batch = results(rect, p2, p3, valid)
    steps = native.pose_under_k
    calls = []

    def far_off(p2, p3, k, rvec, tvec):
        calls.append(1)
        rvec, tvec, _, depth = steps(p2, p3, k, rvec, tvec * 1.05, 0)
        return rvec, tvec, steps(p2, p3, k, rvec, tvec, 0)[2], depth

    monkeypatch.setattr(native, "pose_under_k", far_off)
    single, batch = results(rect, p2, p3, valid)
    assert len(calls) >= 2 * sum(a.fallback is None for a in alone) >= 6
    assert [s.fallback for s in single] == [a.fallback for a in alone]
    assert batch.fallback == alone_batch.fallback
    for got in (np.array([s.rvec for s in single]), batch.rvec):  # SQPnP's last bits follow the arrays' alignment
        np.testing.assert_allclose(got, [a.rvec for a in alone], rtol=1e-9, atol=1e-12)
    errors = [s.reprojection_error_px for s in single]
    np.testing.assert_allclose(errors, [a.reprojection_error_px for a in alone], rtol=1e-9)
