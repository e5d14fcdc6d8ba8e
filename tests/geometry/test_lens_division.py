"""The division model of radial lens distortion (``geometry.lens_division``) and its solvers: Brent's method
(moved here from the board model's tests) and the damped Gauss-Newton fit."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime.geometry import lens_division as ld

CENTRE = np.array([1999.5, 1499.5])
SCALE = 2000.0


def test_the_division_model_by_hand_and_its_inverse():
    """A pixel at r_d = 1 (one half-side from the centre) under k1 = 0.1: u - c = (d - c) / 1.1; the
    centre stays; two terms r_d = 0.5: 1 + k1 / 4 + k2 / 16."""
    d = CENTRE + np.array([[SCALE, 0.0], [0.0, 0.0], [0.0, -SCALE / 2]])
    u = ld.undistort(d, (0.1, 0.0), CENTRE, SCALE)
    np.testing.assert_allclose(u[0], CENTRE + [SCALE / 1.1, 0.0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(u[1], CENTRE)
    two = ld.undistort(d, (0.1, -0.05), CENTRE, SCALE)
    np.testing.assert_allclose(two[2], CENTRE + [0.0, -SCALE / 2 / (1 + 0.1 / 4 - 0.05 / 16)], rtol=0, atol=1e-9)
    for k in ((0.1, 0.0), (0.1, -0.05), (-0.2, 0.03)):
        np.testing.assert_allclose(ld.distort(ld.undistort(d, k, CENTRE, SCALE), k, CENTRE, SCALE), d, atol=1e-9)


def test_gauss_newton_fits_two_terms_within_their_bounds_and_fit_coefficients_starts_it_from_one_term():
    """A misfit whose zero is (0.12, -0.04) is found to K_TOLERANCE; a bound keeps a coefficient inside it."""
    rng = np.random.default_rng(0)
    d = CENTRE + rng.uniform(-1500, 1500, (40, 2))
    target = ld.undistort(d, (0.12, -0.04), CENTRE, SCALE)

    def misfit(k):  # k: k1 alone (one term) or (k1, k2)
        return (ld.undistort(d, ld.coefficients(k), CENTRE, SCALE) - target).ravel()

    found = ld.gauss_newton(misfit, np.array([0.0, 0.0]), np.array([ld.K_RANGE, (-0.25, 0.25)]))
    np.testing.assert_allclose(found, [0.12, -0.04], atol=ld.K_TOLERANCE)
    held = ld.gauss_newton(misfit, np.array([0.0, 0.0]), np.array([ld.K_RANGE, (-0.01, 0.25)]))
    assert held[1] == pytest.approx(-0.01)
    k1, k2 = ld.fit_coefficients(misfit, 2)
    assert abs(k1 - 0.12) < ld.K_TOLERANCE and abs(k2 + 0.04) < ld.K_TOLERANCE
    one = ld.fit_coefficients(misfit, 1)
    assert one[1] == 0.0 and ld.K_RANGE[0] < one[0] < ld.K_RANGE[1]


def test_brent_finds_the_minimiser_to_the_tolerance_in_fewer_steps_than_golden_section():
    calls = []

    def f(x: float) -> float:
        calls.append(x)
        return (x - 0.237) ** 2 + 3.0 * (x - 0.237) ** 4

    assert ld.brent(f, *ld.K_RANGE, ld.K_TOLERANCE) == pytest.approx(0.237, abs=ld.K_TOLERANCE / 2)
    assert len(calls) <= 10  # golden section needs 17 to shrink [-0.5, 0.5] to 1e-3
    calls.clear()
    assert ld.brent(lambda x: f(x + 1.0), *ld.K_RANGE, ld.K_TOLERANCE) == pytest.approx(
        ld.K_RANGE[0], abs=ld.K_TOLERANCE / 2
    )
    assert ld.brent(lambda x: abs(x - 0.1) if x < 0.3 else np.inf, *ld.K_RANGE, ld.K_TOLERANCE) == pytest.approx(
        0.1, abs=ld.K_TOLERANCE / 2
    )
