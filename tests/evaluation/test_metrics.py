"""rho and its noise rule against hand-computed cases; the homography floor against the errors any K
reaches on one plane."""

from __future__ import annotations

import math

import numpy as np

from dimenet.runtime.evaluation.metrics import (
    RHO_NOISE,
    average_noise,
    reduction_ratio,
    reprojection_error_and_variance,
    reprojection_error_under_k,
)
from dimenet.runtime.geometry import homography_floor, k_matrix, project


def test_rho_by_hand():
    assert reduction_ratio(3.0, 1.0, 0.5) == 0.8  # (3 - 1) / (3 - 0.5)
    assert reduction_ratio(3.0, 3.5, 0.5) == -0.2
    assert reduction_ratio(1.0, 0.9, 1.0) is None  # no room to improve


def test_rho_is_none_within_the_noise_of_the_errors():
    # two frames whose e_c have variances 0.01 and 0.04 px^2: Avg(e_c)'s standard error is sqrt(0.05) / 2
    noise = average_noise(np.array([0.01, 0.04]))
    assert math.isclose(noise, math.sqrt(0.05) / 2)
    # the case: e_c - e* = 0.001 px printed rho = -4689 %
    assert reduction_ratio(1.812, 1.859, 1.811, noise) is None
    just_above = 1.812 - RHO_NOISE * noise - 1e-6
    assert reduction_ratio(1.812, 1.812, just_above, noise) == 0.0


def _plane_frame(rng, noise_px):
    K = k_matrix(np.array([3000.0, 3010.0, 2000.0, 1500.0]))
    X = np.column_stack([rng.uniform(-100, 100, (63, 2)), np.zeros(63)])
    x = project(X, K, np.array([0.3, -0.2, 0.1]), np.array([5.0, -10.0, 450.0])) + rng.normal(0, noise_px, (63, 2))
    return x[None], X[None], np.ones((1, 63), bool), K


def test_the_floor_of_an_exact_plane_is_zero_and_no_k_beats_it():
    rng = np.random.default_rng(0)
    x, X, valid, K = _plane_frame(rng, 0.0)
    assert homography_floor(x, X, valid)[0] < 1e-4  # px: the LM's own tolerance
    x, X, valid, K = _plane_frame(rng, 0.7)
    floor = homography_floor(x, X, valid)[0]
    for k in ([3000.0, 3010.0, 2000.0, 1500.0], [2900.0, 2950.0, 2050.0, 1450.0], [3100.0, 3100.0, 1950.0, 1550.0]):
        assert floor <= reprojection_error_under_k(x, X, valid, k_matrix(np.array(k)))[0] + 1e-9
    assert 0.5 < floor < 1.0  # about the noise's mean norm (0.7 * sqrt(pi / 2) = 0.88 px)


def test_the_variance_of_a_frame_error_is_that_of_its_mean():
    rng = np.random.default_rng(1)
    x, X, valid, K = _plane_frame(rng, 0.0)
    X = X.copy()
    X[0, :, 2] = rng.uniform(-50, 50, 63)  # off the plane, so the pose is unique
    x = project(X[0], K, np.array([0.3, -0.2, 0.1]), np.array([5.0, -10.0, 450.0]))[None]
    e, var = reprojection_error_and_variance(x + rng.normal(0, 1.0, x.shape), X, valid, K)
    # norms of 2D Gaussian noise of sigma 1: mean sqrt(pi / 2), variance 2 - pi / 2; the mean of 63 of them
    assert abs(e[0] - math.sqrt(math.pi / 2)) < 0.25
    assert 0.3 * (2 - math.pi / 2) / 63 < var[0] < 2.0 * (2 - math.pi / 2) / 63


def test_ratio_of_rhos_by_hand():
    from dimenet.runtime.evaluation.metrics import ratio_interval

    r = ratio_interval(np.array([2.0, 4.0]), np.array([1.0, 3.0]), np.array([0.0, 2.0]), draws=50)
    assert r.ratio == 0.5 and r.low == r.high == 0.5  # (3 - 2) / (3 - 1), the same on every resampling
    none = ratio_interval(np.array([1.0, 1.0]), np.array([0.5, 0.5]), np.array([1.0, 1.2]))
    assert none.ratio is None and none.low is None  # the reference is no better than K_c


def test_ratio_interval_covers_the_true_ratio_nine_times_in_ten():
    from dimenet.runtime.evaluation.metrics import ratio_interval

    rng = np.random.default_rng(0)
    true_ratio, hits, trials = 0.7, 0, 300
    for t in range(trials):
        e_c = rng.gamma(4.0, 0.75, 200)  # mean 3 px
        e_ref = e_c - rng.normal(1.0, 0.6, 200)  # the reference gains 1 px on average
        e = e_c - rng.normal(true_ratio, 0.8, 200)  # the method 0.7 px
        r = ratio_interval(e_c, e, e_ref, draws=400, seed=t)
        hits += r.low <= true_ratio <= r.high
    assert 0.84 <= hits / trials <= 0.95
