"""Mode map's posterior of K in the compiled core (``dimenet_map_posterior``) against ``map_fit``'s numpy
(the K block symmetrised, then ``Uncertainty.map_covariance``), to the bit: with and without the data
correlation and the data bias, posteriors wider than the prior, NaNs; and through ``map_fit`` under both
implementations."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import constant_uncertainty, random_frames

from dimenet.runtime import native
from dimenet.runtime.geometry import k_matrix, k_params, solve_pnp_start
from dimenet.runtime.rectify.map_fit import map_fit, map_posterior

pytestmark = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")


def uncertainties(rng):
    base = constant_uncertainty(1.0)
    yield None
    yield base
    yield replace(base, data_correlation=np.array([0.0, 0.4, 0.6, 1.0]))
    yield replace(base, data_bias=np.array([0.0, 0.5, 1.5, 3.0]))
    for _ in range(20):
        yield replace(
            base,
            data_correlation=rng.uniform(0.0, 1.0, 4) * (rng.random(4) < 0.7),
            noise_scale_px=float(rng.uniform(0.1, 5.0)),
            data_bias=rng.uniform(0.0, 3.0, 4) * (rng.random(4) < 0.7),
        )


def both(cov, K_cov_net, noise_px, u):
    out = {}
    for name in ("python", "c"):
        with native.using(name):
            out[name] = map_posterior(cov, K_cov_net, noise_px, u)
    return out["python"], out["c"]


def test_the_core_gives_map_fits_posterior_to_the_bit():
    rng = np.random.default_rng(12)
    for u in uncertainties(rng):
        for _ in range(25):
            A = rng.normal(size=(10, 10))
            cov = A @ A.T * 10.0 ** rng.uniform(-3, 3) + rng.normal(0.0, 1e-9, (10, 10))  # not quite symmetric
            B = rng.normal(size=(4, 4))
            K_cov_net = B @ B.T * 10.0 ** rng.uniform(-3, 3)  # some posteriors wider than the prior: r > 1
            noise_px = float(10.0 ** rng.uniform(-2, 1))
            reference, compiled = both(cov, K_cov_net, noise_px, u)
            np.testing.assert_array_equal(compiled, reference)
    cov = np.eye(10)
    cov[7, 7] = np.nan
    reference, compiled = both(cov, np.eye(4), 1.0, replace(constant_uncertainty(1.0), data_correlation=np.ones(4)))
    np.testing.assert_array_equal(compiled, reference)  # NaN where numpy has it
    assert np.isnan(compiled[1]).all() and not np.isnan(compiled[0, 0])


def test_map_fit_gives_the_same_posterior_under_both_implementations():
    x, X, K, _, _ = random_frames(np.random.default_rng(2), 1, 120, noise_px=2.0)
    k_net = k_params(K[0]) + [6.0, -5.0, 8.0, -7.0]
    start = solve_pnp_start(x[0], X[0], k_matrix(k_net))
    u = replace(constant_uncertainty(1.0), data_correlation=np.array([0.0, 0.4, 0.6, 1.0]), data_bias=np.ones(4))
    fits = {}
    for name in ("python", "c"):
        with native.using(name):
            fits[name] = map_fit(x[0], X[0], k_net, np.diag([4.0, 4.0, 100.0, 100.0]), *start, uncertainty=u)
    np.testing.assert_array_equal(fits["c"].K_cov, fits["python"].K_cov)
    assert np.all(np.diag(fits["c"].K_cov) > 0)


def test_bad_arrays_are_refused():
    core = native._compiled()[0]
    args = [np.eye(10), np.eye(4), 1.0, np.zeros(4), 2.0, np.zeros(4), np.empty((4, 4))]
    assert core.map_posterior(*args) is None
    np.testing.assert_array_equal(args[-1], np.eye(4))
    with pytest.raises(ValueError):
        core.map_posterior(np.eye(9), *args[1:])
    with pytest.raises(TypeError, match="k_cov_out"):
        core.map_posterior(*args[:-1], np.empty((4, 4)).T)
    with pytest.raises(TypeError, match="7 arguments"):
        core.map_posterior(*args[:-1])
