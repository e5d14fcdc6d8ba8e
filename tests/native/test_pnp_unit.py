"""The PnP's unit in the compiled core (``dimenet_power_of_two_unit``) against its numpy reference
(``geometry.pnp.power_of_two_unit``): the same power of two to the bit on every size of frame (numpy's
pairwise sums split at 128 values), scenes from 1e-300 to 1e308 mm, non-finite points; and SQPnP's pose
through ``native.solve_pnp_start`` equal to the reference's."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import native
from dimenet.runtime.geometry import solve_pnp_start
from dimenet.runtime.geometry.pnp import power_of_two_unit

pytestmark = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")


def core_unit(points_3d: np.ndarray) -> float:
    return native._compiled()[0].power_of_two_unit(points_3d)


@pytest.mark.parametrize("scale", [1e-300, 1e-3, 1.0, 700.0, 1e12, 1e300, 1.7e308])
def test_the_unit_is_the_references_on_every_size(scale):
    rng = np.random.default_rng(7)
    for n in [*range(1, 200, 3), 1000, 2731, 9000]:
        with np.errstate(over="ignore"):  # 1.7e308 x 2: some coordinates are inf, and the unit is 1
            points = rng.standard_normal((n, 3)) * scale * rng.uniform(0.5, 2.0)
        points[rng.random((n, 3)) < 0.05] *= rng.uniform(0.0, 1.0)
        want = power_of_two_unit(points)
        got = core_unit(points)
        assert got == want, (n, scale)
        assert np.frexp(got)[0] == 0.5


def test_the_unit_of_zero_and_non_finite_points_is_one():
    for value in (0.0, np.inf, -np.inf, np.nan, 5e-324):  # a lone denormal: an RMS norm that rounds to 0
        points = np.ones((5, 3))
        points[2, 1] = value
        if value in (0.0, 5e-324):
            points[:] = 0.0
            points[2, 1] = value
        assert core_unit(points) == power_of_two_unit(points) == 1.0


def test_the_unit_of_a_scene_near_the_largest_float_is_finite():
    points = np.full((4, 3), 1.0e308)  # RMS norm 1.7e308, nearest 2^1024: the largest finite power is taken
    assert core_unit(points) == power_of_two_unit(points) == 2.0**1023


def test_the_unit_of_an_exact_scene():
    # RMS norm 300 mm: the nearest power of two is 256; 400 mm: 512
    for norm, unit in ((300.0, 256.0), (400.0, 512.0)):
        points = np.array([[norm, 0, 0], [0, norm, 0], [0, 0, norm], [-norm, 0, 0]])
        assert core_unit(points) == power_of_two_unit(points) == unit


def test_sqpnp_through_the_core_is_the_references():
    x, X, _, _, _ = random_frames(np.random.default_rng(3), frames=20, points=50, noise_px=0.5)
    with native.using("c"):
        for p2, p3 in zip(x, X):
            rvec, tvec = native.solve_pnp_start(p2, p3, K_TEST)
            want_r, want_t = solve_pnp_start(p2, p3, K_TEST)
            assert np.array_equal(rvec, want_r) and np.array_equal(tvec, want_t)
            # a list, or float32 points: the reference takes them
            assert np.array_equal(native.solve_pnp_start(p2, p3.tolist(), K_TEST)[1], want_t)
            assert np.allclose(native.solve_pnp_start(p2, p3.astype(np.float32), K_TEST)[1], want_t, rtol=1e-5)
