"""Fitting the uncertainty model: the noise model, its data correlation, and refused input."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from helpers import constant_uncertainty

from dimenet.runtime.errors import InputError
from dimenet.runtime.evaluation.uncertainty_fit import coverage, fit_data_bias, fit_data_correlation, fit_uncertainty
from dimenet.runtime.rectify.uncertainty import MAX_DATA_BIAS, NOISE_SCALE_PX, Uncertainty


def test_uncertainty_fit_recovers_a_known_noise_model():
    rng = np.random.default_rng(0)
    n = 4000
    stats = np.c_[
        np.log(rng.uniform(60, 320, n)),
        np.log(rng.uniform(8, 48, n)),
        np.log(rng.uniform(0.3, 10, n)),
        np.log(rng.uniform(1e-6, 0.3, n)),
    ]
    true_coef = np.array(
        [
            [1.0, -0.5, 0.0, 0.3, -0.1],
            [0.5, 0.0, -0.2, 0.6, 0.0],
            [2.0, -0.3, -0.1, 0.0, -0.2],
            [1.5, 0.0, 0.0, 0.4, -0.05],
        ]
    )
    corr = np.array([[1, 0.8, 0, 0], [0.8, 1, 0, 0], [0, 0, 1, -0.3], [0, 0, -0.3, 1.0]])
    sigma = np.exp(np.c_[np.ones(n), stats] @ true_coef.T)
    residuals = (rng.multivariate_normal(np.zeros(4), corr, n)) * sigma
    model = fit_uncertainty(residuals, stats)
    np.testing.assert_allclose(model.coef[:, 1:], true_coef[:, 1:], atol=0.05)  # slopes
    np.testing.assert_allclose(model.sigma(stats), sigma, rtol=0.15)
    np.testing.assert_allclose(model.correlation, corr, atol=0.05)
    fresh = rng.multivariate_normal(np.zeros(4), corr, n) * sigma
    for share in coverage(fresh, np.zeros_like(fresh), model.covariance(stats)).values():
        assert 0.65 < share < 0.71
    again = Uncertainty.from_dict(json.loads(json.dumps(model.to_dict())), 48)
    np.testing.assert_array_equal(again.coef, model.coef)
    one = model.frame_covariance(100, 20, 2.5, 0.01)
    np.testing.assert_allclose(one, model.covariance(np.log([[100, 20, 2.5, 0.01]]))[0], rtol=1e-12)


def test_uncertainty_refuses_bad_input():
    with pytest.raises(InputError, match="needs >= 20 frames"):
        fit_uncertainty(np.ones((5, 4)), np.ones((5, 4)))
    with pytest.raises(InputError, match=r"statistics must be \(F, 4\)"):
        fit_uncertainty(np.ones((40, 4)), np.ones((40, 3)))
    with pytest.raises(ValueError, match="not positive definite"):
        Uncertainty.from_dict({"coef": np.zeros((4, 4)).tolist(), "correlation": np.ones((4, 4)).tolist()}, 48)
    with pytest.raises(ValueError, match="distinct names"):
        Uncertainty.from_dict(
            {
                "statistics": ["1", "log_points", "log_depth"],
                "coef": np.zeros((4, 3)).tolist(),
                "correlation": np.eye(4).tolist(),
            },
            48,
        )


def test_data_correlation_fit_recovers_a_known_correlation():
    rng = np.random.default_rng(0)
    n = 20000
    sigma = rng.uniform(0.5, 5.0, (n, 4))
    ratio = rng.uniform(0.05, 0.95, (n, 4))
    noise = rng.uniform(0.3, 8.0, n)
    rho = np.array([0.0, 0.3, 0.8, 0.0])
    w = noise**2 / (noise**2 + NOISE_SCALE_PX**2)
    widened = sigma * np.sqrt(1 + 2 * rho * w[:, None] * np.sqrt(ratio * (1 - ratio)))
    errors = rng.normal(size=(n, 4)) * widened
    errors[:, 0] *= 0.8  # over-covered already: no correlation to add
    errors[:, 3] *= 3.0  # beyond any correlation: the largest, 1
    np.testing.assert_allclose(fit_data_correlation(errors, sigma, ratio, noise), [0.0, 0.3, 0.8, 1.0], atol=0.05)
    with pytest.raises(InputError, match=r"\(F, 4\)"):
        fit_data_correlation(errors[:, :3], sigma, ratio, noise)
    with pytest.raises(InputError, match="finite"):
        fit_data_correlation(errors, sigma * np.nan, ratio, noise)
    with pytest.raises(ValueError, match=r"data_correlation must be 4 values in \[0, 1\]"):
        replace(constant_uncertainty(1.0), data_correlation=np.array([0.0, 0.0, 1.5, 0.0]))


def test_data_bias_fit_recovers_a_known_share_of_the_network_sigma():
    """MAP errors = posterior noise (widened by a known correlation) + b times the network's error:
    the fit finds the b with which 95.45 % of the frames lie within 2 sigma on every parameter
    (4 independent Gaussian parameters at 2 sigma jointly: 83 %, so b is above the true one); a
    covered set gets 0, one beyond any b the largest."""
    rng = np.random.default_rng(1)
    n = 20000
    sigma = rng.uniform(0.5, 5.0, (n, 4))
    ratio = rng.uniform(0.05, 0.95, (n, 4))
    noise = rng.uniform(0.3, 8.0, n)
    net = rng.uniform(2.0, 40.0, (n, 4))
    rho = np.array([0.0, 0.5, 0.2, 0.0])
    w = noise**2 / (noise**2 + NOISE_SCALE_PX**2)
    widened2 = sigma**2 * (1 + 2 * rho * w[:, None] * np.sqrt(ratio * (1 - ratio)))
    z = rng.normal(size=(n, 4))
    b = 0.8
    errors = z * np.sqrt(widened2 + (b * net) ** 2)
    fitted = fit_data_bias(errors, sigma, ratio, noise, net, rho)
    assert np.all(fitted == fitted[0]) and fitted[0] > b
    inside = np.all(errors**2 <= 4 * (widened2 + (fitted[0] * net) ** 2), 1)
    assert abs(inside.mean() - 0.9545) < 0.002
    covered = z * np.sqrt(widened2) * 0.5  # the posterior alone covers them
    assert np.all(fit_data_bias(covered, sigma, ratio, noise, net, rho) == 0.0)
    assert np.all(fit_data_bias(100.0 * net, sigma, ratio, noise, net, rho) == MAX_DATA_BIAS)
    with pytest.raises(InputError, match=r"\(F, 4\)"):
        fit_data_bias(errors, sigma, ratio, noise, net[:, :3], rho)
