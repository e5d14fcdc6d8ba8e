import cv2
import numpy as np
from helpers import random_frames

from dimenet.runtime import geometry as g
from dimenet.runtime.geometry import least_squares as ls


def test_pose_optimum_matches_opencv_lm():
    rng = np.random.default_rng(0)
    x, X, K, *_ = random_frames(rng, frames=3, points=80, noise_px=0.5)
    res = ls.solve_pnp(x, X, np.ones(x.shape[:2]), K)
    for b in range(3):
        _, r, t = cv2.solvePnP(X[b], x[b], K[b], None, flags=cv2.SOLVEPNP_ITERATIVE)
        r, t = cv2.solvePnPRefineLM(X[b], x[b], K[b], None, r, t)
        np.testing.assert_allclose(res.rvec[b], r.ravel(), atol=1e-9)
        np.testing.assert_allclose(res.tvec[b], t.ravel(), atol=1e-6)


def test_calibrate_recovers_k_exactly_without_noise_and_ignores_masked_points():
    rng = np.random.default_rng(1)
    x, X, K, rvec, tvec = random_frames(rng, frames=3, points=40)
    w = np.ones(x.shape[:2])
    w[:, :5] = 0.0
    x[:, :5] += 1e3  # garbage on masked points must have no effect
    res = ls.calibrate(x, X, w)
    np.testing.assert_allclose(res.K, K, atol=1e-6)
    np.testing.assert_allclose(res.rvec, rvec, atol=1e-9)
    assert np.all(res.cost < 1e-12)


def test_calibrate_reduces_cost_below_fixed_k():
    rng = np.random.default_rng(2)
    x, X, K, *_ = random_frames(rng, frames=2, points=100, noise_px=0.4)
    w = np.ones(x.shape[:2])
    wrong = K.copy()
    wrong[:, 0, 2] += 25.0
    fixed = ls.solve_pnp(x, X, w, wrong)
    joint = ls.calibrate(x, X, w)
    assert np.all(joint.cost < fixed.cost)
    # The joint fit moves cx back towards the truth it was pushed 25 px away from.
    assert np.all(np.abs(g.k_params(joint.K)[:, 2] - g.k_params(K)[:, 2]) < 10.0)
