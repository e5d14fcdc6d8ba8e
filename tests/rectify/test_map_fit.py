"""Beyond the paper: the MAP fit of K (map_fit, map_rectify), from vague to sharp priors and on planar views."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from helpers import constant_uncertainty, random_frames

from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import calibrate, k_matrix, k_params, project, solve_pnp_start
from dimenet.runtime.geometry.map_step import principal_point_turn
from dimenet.runtime.rectify.map_fit import map_fit, map_rectify
from dimenet.runtime.rectify.uncertainty import NOISE_SCALE_PX

K_NET_OFFSET = np.array([6.0, -5.0, 8.0, -7.0])  # px: the "network's" error in the MAP tests


def test_map_fit_widens_its_posterior_by_the_data_correlation():
    x, X, K = _frame(np.random.default_rng(1), noise_px=3.0)
    k_net = k_params(K) + K_NET_OFFSET
    start = solve_pnp_start(x, X, k_matrix(k_net))
    prior = np.diag([4.0, 4.0, 100.0, 100.0])
    plain = map_fit(x, X, k_net, prior, *start)
    independent = map_fit(x, X, k_net, prior, *start, uncertainty=constant_uncertainty(1.0))
    np.testing.assert_array_equal(independent.K_cov, plain.K_cov)  # rho = 0: nothing to widen
    u = replace(constant_uncertainty(1.0), data_correlation=np.array([0.0, 0.4, 0.6, 1.0]))
    widened = map_fit(x, X, k_net, prior, *start, uncertainty=u)
    np.testing.assert_array_equal(widened.k, plain.k)  # the estimate itself does not change
    assert 2.0 < plain.noise_px < 4.0  # the frame's 3 px noise, estimated
    scale = np.sqrt(
        1
        + 2
        * u.data_correlation
        * plain.noise_px**2
        / (plain.noise_px**2 + NOISE_SCALE_PX**2)
        * np.sqrt((r := np.diag(plain.K_cov) / np.diag(prior)) * (1 - r))
    )
    np.testing.assert_allclose(widened.K_cov, plain.K_cov * np.outer(scale, scale), rtol=1e-12)
    assert scale[0] == 1.0 and np.all(scale[1:] > 1.0)


def _frame(rng, planar=False, noise_px=0.5, points=120):
    x, X, K, rvec, tvec = random_frames(rng, 1, points, noise_px=noise_px, planar=planar)
    return x[0], X[0], K[0]


def test_map_with_a_vague_prior_is_self_calibration():
    x, X, K = _frame(np.random.default_rng(1))
    k_net = k_params(K) + K_NET_OFFSET
    start = solve_pnp_start(x, X, k_matrix(k_net))
    fit = map_fit(x, X, k_net, np.eye(4) * 1e10, *start, iterations=10)
    self_k = k_params(calibrate(x[None], X[None], np.ones((1, len(x)))).K[0])
    np.testing.assert_allclose(fit.k, self_k, atol=1e-3)
    # One step (the runtime's default) already removes > 97 % of the start's 6-8 px error.
    np.testing.assert_allclose(map_fit(x, X, k_net, np.eye(4) * 1e10, *start).k, self_k, atol=0.2)


def test_one_step_from_the_c0_pose_turned_to_k_net_lands_at_the_optimum():
    x, X, K = _frame(np.random.default_rng(1))
    k_net = k_params(K) + K_NET_OFFSET
    self_k = k_params(calibrate(x[None], X[None], np.ones((1, len(x)))).K[0])
    K_c = k_matrix(k_net - [10.0, 10.0, 40.0, 30.0])  # the runtime's start: the pose under K_c, f and c off k_net
    rvec, tvec = solve_pnp_start(x, X, K_c)
    turn = cv2.Rodrigues(principal_point_turn(K_c, k_net))[0]
    R, t = turn @ cv2.Rodrigues(rvec)[0], turn @ tvec
    # Turned, the pose images the points under k_net about where they were under K_c (first order).
    under_k_c = project(X, K_c, rvec, tvec)
    turned = np.abs(project(X, k_matrix(k_net), cv2.Rodrigues(R)[0].ravel(), t) - under_k_c).max()
    assert turned < 0.25 * np.abs(project(X, k_matrix(k_net), rvec, tvec) - under_k_c).max()
    one_step = map_fit(x, X, k_net, np.eye(4) * 1e10, rvec, tvec, K_start=K_c).k
    unturned = map_fit(x, X, k_net, np.eye(4) * 1e10, rvec, tvec).k
    assert np.abs(one_step - self_k).max() < 0.2 < np.abs(unturned - self_k).max()


def test_map_with_a_sharp_prior_keeps_the_network_k_and_the_pnp_pose():
    x, X, K = _frame(np.random.default_rng(2))
    k_net = k_params(K) + K_NET_OFFSET
    start = solve_pnp_start(x, X, k_matrix(k_net))
    fit = map_fit(x, X, k_net, np.eye(4) * 1e-10, *start, iterations=5)
    np.testing.assert_allclose(fit.k, k_net, atol=1e-6)
    assert np.all(np.linalg.eigvalsh(fit.K_cov) > 0) and np.all(np.diag(fit.K_cov) <= 1e-10 * (1 + 1e-6))


def test_map_rectify_refuses_a_fit_whose_step_raised_the_cost():
    x, X, K, rvec, tvec = random_frames(np.random.default_rng(0), 1, 60, noise_px=0.5)
    x, X, k, bounds = x[0], X[0], k_params(K[0]), np.stack([k_params(K[0]) - 500, k_params(K[0]) + 500], -1)
    near = map_rectify(x, X, k, np.eye(4) * 25.0, bounds, K[0], pose=(rvec[0], tvec[0]))
    assert near[1] is None and near[0].steps == 1
    # From a start 1 rad off, the one Gauss-Newton step overshoots: the start is no answer.
    far = map_rectify(x, X, k, np.eye(4) * 25.0, bounds, K[0], pose=(rvec[0] + [1.0, 0.0, 0.0], tvec[0]))
    assert far == (None, "the MAP step did not lower the cost") and far[1].code == "map_no_step"


def test_map_rectify_gives_way_where_the_points_fix_no_pose():
    # One point repeated: the Hessian is singular whatever the prior on K.
    x, X, K, rvec, tvec = random_frames(np.random.default_rng(0), 1, 60, noise_px=0.5)
    X_one = np.repeat(X[0][:1], 60, 0)
    x_one = project(X_one, K[0], rvec[0], tvec[0])
    k, bounds = k_params(K[0]), np.stack([k_params(K[0]) - 500, k_params(K[0]) + 500], -1)
    with pytest.raises(InputError, match="not positive definite"):
        map_fit(x_one, X_one, k, np.eye(4) * 25.0, rvec[0], tvec[0])
    got = map_rectify(x_one, X_one, k, np.eye(4) * 25.0, bounds, K[0], pose=(rvec[0], tvec[0]))
    assert got == (None, "the points fix no MAP pose (its Hessian is not positive definite)")
    assert got[1].code == "map_no_pose" and not got[1].refusal
    # Points on one line: the turn about it is free. Whether the Cholesky factorisation fails on the rounded
    # Hessian or its step fails to lower the cost, DIME-Net's K stands with a note.
    X_line = np.outer(np.linspace(-1.0, 1.0, 60), X[0][1] - X[0][0]) + X[0][0]
    x_line = project(X_line, K[0], rvec[0], tvec[0])
    fit, note = map_rectify(x_line, X_line, k, np.eye(4) * 25.0, bounds, K[0], pose=(rvec[0], tvec[0]))
    assert fit is None and note.code in ("map_no_pose", "map_no_step") and not note.refusal


def test_map_on_one_planar_view_follows_the_prior_where_the_data_says_nothing():
    x, X, K = _frame(np.random.default_rng(3), planar=True)
    with pytest.raises(Exception, match="coplanar"):
        calibrate(x[None], X[None], np.ones((1, len(x))))
    k_net = k_params(K) + K_NET_OFFSET
    prior = np.diag([25.0, 25.0, 25.0, 25.0])
    fit = map_fit(x, X, k_net, prior, *solve_pnp_start(x, X, k_matrix(k_net)), iterations=10)
    assert np.all(np.isfinite(fit.k)) and np.all(np.abs(fit.k - k_params(K)) < 4 * 5.0)
    # The posterior is never wider than the prior (the data only add information).
    assert np.all(np.linalg.eigvalsh(prior - fit.K_cov) >= -1e-9)


@pytest.mark.parametrize("depth_mm, code", [(350.0, None), (-1.0, "map_behind_camera"), (np.nan, "map_behind_camera")])
def test_map_rectify_refuses_a_fit_with_a_point_behind_the_camera(monkeypatch, depth_mm, code):
    # The fit's smallest depth (the kernel's, at the MAP pose) decides; NaN, which no comparison passes, too.
    from dimenet.runtime.rectify import map_fit as module

    x, X, K = _frame(np.random.default_rng(3))
    k_net = k_params(K)
    fit = map_fit(x, X, k_net, np.eye(4) * 25.0, *solve_pnp_start(x, X, K), K_start=K)
    assert fit.steps == 1 and fit.depth_mm > 0
    monkeypatch.setattr(module, "map_fit", lambda *args, **kwargs: replace(fit, depth_mm=depth_mm))
    result, why = map_rectify(x, X, k_net, np.eye(4) * 25.0, np.array([[-1e9, 1e9]] * 4), K)
    assert (why is None and result.depth_mm == depth_mm) if code is None else (result is None and why.code == code)
