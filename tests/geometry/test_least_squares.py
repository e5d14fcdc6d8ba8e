import cv2
import numpy as np
import pytest
from helpers import random_frames

from dimenet.runtime import geometry as g
from dimenet.runtime.errors import CalibrationError
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


def test_map_normal_equations_are_the_lm_cores_jacobian_in_the_left_pose_parameters():
    """geometry.frame_normal_equations (MAP's closed form) is the LM core's Jacobian, re-expressed
    for the pose perturbed on the left of X_C (w, tau) instead of on R and t (d, dt): to first
    order d = w and dt = w x t + tau, so J_map = J_lm T."""
    rng = np.random.default_rng(7)
    x, X, K, rvec, tvec = random_frames(rng, frames=1, points=40, noise_px=0.8)
    R, k, sqrt_w = g.rvec_to_matrix(rvec), g.k_params(K), np.ones(x.shape[:2])
    r, Xc, z, xn, yn = ls.residuals(x, X, sqrt_w, k, R, tvec)
    J = ls.jacobian(sqrt_w, k, Xc, tvec, z, xn, yn, fit_k=True).reshape(-1, 10)  # (2N, 10)
    T = np.eye(10)
    T[3:6, 0:3] = -g.skew(tvec[0])
    J_left = J @ T
    JJ, Jr, rss, residuals = g.frame_normal_equations(g.camera_xy_inverse_depth(X[0], R[0], tvec[0]), x[0], k[0])
    np.testing.assert_allclose(JJ, J_left.T @ J_left, rtol=1e-9, atol=1e-9 * np.abs(JJ).max())
    np.testing.assert_allclose(Jr, J_left.T @ r.reshape(-1), rtol=1e-9, atol=1e-9 * np.abs(Jr).max())
    assert abs(rss - (r**2).sum()) <= 1e-9 * rss
    np.testing.assert_allclose(residuals.T, r[0], atol=1e-9)


def test_damped_solve_gives_a_singular_frame_no_step_and_solves_the_others():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 10, 10))
    H = A @ A.transpose(0, 2, 1) + np.eye(10)
    H[1] = np.outer(A[1, 0], A[1, 0])  # rank 1: LAPACK's solve raises for the whole batch
    g = rng.normal(size=(3, 10))
    x = ls.damped_solve(H, g)
    np.testing.assert_array_equal(x[1], 0.0)
    for b in (0, 2):
        np.testing.assert_allclose(H[b] @ x[b], g[b], atol=1e-9)


def test_partial_calibration_gives_nan_and_the_reason_for_a_planar_frame_and_fits_the_others_alone():
    """calibrate(partial=True), the one per-frame calibration (K*, the self baseline): a frame that gives
    no K is NaN with its reason and leaves the other frames' fits as they are on their own; without
    ``partial`` the same frame raises, named."""
    rng = np.random.default_rng(4)
    x, X, K, *_ = random_frames(rng, frames=3, points=40, noise_px=0.3)
    X[1, :, 2] = 0.0  # frame 1 planar: K not observable from it
    w = np.ones(x.shape[:2])
    res = ls.calibrate(x, X, w, partial=True)
    assert res.reasons[0] is None and res.reasons[2] is None and "coplanar" in res.reasons[1]
    assert np.all(np.isnan(res.K[1])) and np.all(np.isnan(res.rvec[1])) and np.isnan(res.cost[1])
    alone = ls.calibrate(x[[0, 2]], X[[0, 2]], w[[0, 2]])
    np.testing.assert_array_equal(res.K[[0, 2]], alone.K)
    np.testing.assert_array_equal(res.tvec[[0, 2]], alone.tvec)
    with pytest.raises(CalibrationError, match="frame 1: .*coplanar"):
        ls.calibrate(x, X, w)


def test_the_shared_lm_step_and_damping_rule_by_hand():
    """H = diag(4, 1e-13) (the second below DIAGONAL_FLOOR), g = (2, 1), damping 0.5: the damped system is
    diag(4 + 0.5 * 4, 1e-13 + 0.5 * 1e-12) and the step -(2 / 6, 1 / 6e-13); a batch of two steps alike, the
    one with a singular damped system (damping 0 on a zero H) takes none; the damping falls tenfold after
    a step that lowers the cost and grows tenfold after one that does not."""
    H = np.diag([4.0, 1e-13])
    np.testing.assert_allclose(ls.damped(H, 0.5), np.diag([6.0, 1e-13 + 0.5e-12]), rtol=1e-15)
    np.testing.assert_allclose(ls.lm_step(H, np.array([2.0, 1.0]), 0.5), [-2.0 / 6.0, -1.0 / 6e-13], rtol=1e-12)
    batch = ls.lm_step(np.stack([H, np.zeros((2, 2))]), np.array([[2.0, 1.0], [1.0, 1.0]]), np.array([0.5, 0.0]))
    np.testing.assert_allclose(batch[0], [-2.0 / 6.0, -1.0 / 6e-13], rtol=1e-12)
    np.testing.assert_array_equal(batch[1], 0.0)
    np.testing.assert_allclose(ls.next_damping(np.array([1e-3, 1e-3]), np.array([True, False])), [1e-4, 1e-2])
