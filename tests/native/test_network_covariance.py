"""The network's covariance of one frame in the compiled core (``dimenet_network_covariance``) against
``Uncertainty.frame_covariance_reference``, to the bit: the bundled models' uncertainties and random ones (every
subset of the statistics, in any order), statistics from the floors to overflow, NaN; the reference against numpy's
matrix form to rounding and against a hand-computed case."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from dimenet.runtime import native
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.uncertainty import D_FLOOR_PX, STATISTICS, T_FLOOR, Uncertainty

pytestmark = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")


def random_uncertainty(rng, statistics) -> Uncertainty:
    A = rng.normal(size=(4, 4))
    d = np.sqrt(np.diag(A @ A.T + np.eye(4)))
    correlation = (A @ A.T + np.eye(4)) / np.outer(d, d)
    coef = np.c_[rng.normal(0.0, 2.0, 4), rng.normal(0.0, 0.7, (4, len(statistics)))]
    return Uncertainty(coef=coef, correlation=correlation, statistics=statistics)


def random_statistics(rng):
    yield 1, 1, 0.0, 0.0  # both floors
    yield 100_000, 64, 1000.0, 1 / 3
    yield 320, 40, math.nan, 0.01
    yield 320, 40, 1.3, math.nan
    for _ in range(40):
        yield (
            int(rng.integers(1, 5000)),
            int(rng.integers(1, 200)),
            float(10.0 ** rng.uniform(-3, 3)),
            float(10.0 ** rng.uniform(-8, -0.5)),
        )


def both(u: Uncertainty, stats) -> tuple[np.ndarray, np.ndarray]:
    with native.using("c"):
        compiled = u.frame_covariance(*stats)
    with native.using("python"):
        reference = u.frame_covariance(*stats)
    return reference, compiled


def test_the_core_gives_the_reference_to_the_bit():
    rng = np.random.default_rng(7)
    models = [load_model(name).spec.uncertainty for name in ("default", "paper-rig")]
    subsets = [s for r in range(5) for s in itertools.permutations(STATISTICS, r)]
    randoms = [random_uncertainty(rng, subsets[i]) for i in rng.choice(len(subsets), 30, replace=False)]
    checked = 0
    for u in models + randoms:
        for stats in random_statistics(rng):
            reference, compiled = both(u, stats)
            np.testing.assert_array_equal(compiled, reference)
            checked += 1
    assert checked == 32 * 44


def test_overflow_gives_inf_in_both():
    u = Uncertainty(coef=np.array([[800.0], [0.0], [0.0], [0.0]]), correlation=np.eye(4), statistics=())
    reference, compiled = both(u, (10, 2, 1.0, 0.1))
    np.testing.assert_array_equal(compiled, reference)
    assert reference[0, 0] == math.inf and reference[1, 1] == 1.0 and np.isnan(reference[0, 1])  # inf * 0


def test_the_reference_by_hand_and_against_the_matrix_form():
    coef = np.array([[0.5, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.5, 0.5], [-1.0, 0.0, 0.0]])
    correlation = np.eye(4)
    correlation[0, 1] = correlation[1, 0] = 0.5
    u = Uncertainty(coef=coef, correlation=correlation, statistics=("log_pmd", "log_points"))
    n, d = 4, 0.02  # d below the floor
    sigma = [math.exp(0.5) * D_FLOOR_PX, n, math.e * math.sqrt(D_FLOOR_PX * n), math.exp(-1.0)]
    expected = np.outer(sigma, sigma) * correlation
    with native.using("python"):
        np.testing.assert_allclose(u.frame_covariance(n, 7, d, 0.2), expected, rtol=1e-14)
    rng = np.random.default_rng(3)
    for u in [load_model("default").spec.uncertainty, random_uncertainty(rng, STATISTICS[1:3])]:
        stats = (320, 40, 1.3, 0.002)
        z = np.log([stats[0], stats[1], max(stats[2], D_FLOOR_PX), max(stats[3], T_FLOOR)])
        s = np.exp(u.coef @ np.r_[1.0, z[[STATISTICS.index(name) for name in u.statistics]]])
        with native.using("python"):
            np.testing.assert_allclose(u.frame_covariance(*stats), np.outer(s, s) * u.correlation, rtol=1e-13)


def test_bad_arguments_are_refused():
    core = native._compiled()[0]
    u = load_model("default").spec.uncertainty
    out = np.empty((4, 4))
    args = [320, 40, 1.3, 0.01, D_FLOOR_PX, T_FLOOR, bytes([0, 1, 2, 3]), u.coef, u.correlation, out]
    assert core.network_covariance(*args) is None
    with pytest.raises(ValueError, match="counts >= 1"):
        core.network_covariance(0, *args[1:])
    with pytest.raises(ValueError, match="counts >= 1"):
        core.network_covariance(*args[:6], bytes([0, 1, 2, 4]), *args[7:])
    with pytest.raises(ValueError, match="len\\(columns\\)"):
        core.network_covariance(*args[:6], bytes([0, 1, 2]), *args[7:])
    with pytest.raises(TypeError, match="k_cov_out"):
        core.network_covariance(*args[:-1], np.empty((4, 4)).T)
    with pytest.raises(TypeError, match="10 arguments"):
        core.network_covariance(*args[:-1])
