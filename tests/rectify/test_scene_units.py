"""A scene's unit changes nothing: the same frame in units from 1e-6 mm to the input rule's limit
(1e12) gets the same Delta K, K and pose (scaled) as in mm (issue 48 #1: at 3.6e11 the data step's
Cholesky inverse came back as zeros, a silent zero step)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import example_camera

from dimenet.runtime import Rectifier
from dimenet.runtime.assets import asset
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import prior_posterior, solve_pnp_start

SCALES = (1e-6, 1e-3, 25.4, 1e6, 1e9, None)  # None: the largest coordinate at 3.6e11


def _frames():
    with np.load(asset("example_frames.npz"), allow_pickle=False) as d:
        return [(d["points_2d"][b][d["valid"][b]], d["points_3d"][b][d["valid"][b]]) for b in range(4)]


@pytest.mark.parametrize("name", ["default", "paper-rig"])
@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_delta_k_is_the_same_in_any_unit(name, mode):
    camera = example_camera()
    rectifier = Rectifier.load(name, K_c=camera.K, image_size=camera.image_size, mode=mode)
    for p2, p3 in _frames():
        mm = rectifier.rectify(p2, p3)
        for s in SCALES:
            s = 3.6e11 / np.abs(p3).max() if s is None else s
            scaled = rectifier.rectify(p2, p3 * s)
            assert np.abs(scaled.delta_k - mm.delta_k).max() <= 1e-6, (name, mode, s)
            assert np.abs(scaled.K - mm.K).max() <= 1e-6
            assert scaled.fallback == mm.fallback
            np.testing.assert_allclose(scaled.tvec, mm.tvec * s, rtol=1e-9, atol=0)


def test_pnp_start_is_unit_equivariant():
    for p2, p3 in _frames():
        K = example_camera().K
        rvec, tvec = solve_pnp_start(p2, p3, K)
        for s in (1e-6, 1e9):
            rvec_s, tvec_s = solve_pnp_start(p2, p3 * s, K)
            np.testing.assert_allclose(rvec_s, rvec, rtol=0, atol=1e-12)
            np.testing.assert_allclose(tvec_s / s, tvec, rtol=1e-12)


def test_the_pnp_unit_of_extreme_coordinates_warns_of_nothing():
    import warnings

    from dimenet.runtime.geometry.pnp import power_of_two_unit

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert power_of_two_unit(np.full((4, 3), 1e300)) == 2.0 ** round(np.log2(np.sqrt(3) * 1e300))
        assert power_of_two_unit(np.full((4, 3), 1e-300)) == 2.0 ** round(np.log2(np.sqrt(3) * 1e-300))
        assert power_of_two_unit(np.zeros((4, 3))) == 1.0
        assert power_of_two_unit(np.full((4, 3), np.inf)) == 1.0


def test_a_singular_hessian_is_an_error_not_a_zero_step():
    JJ = np.zeros((10, 10))  # no point fixes the pose
    with pytest.raises(InputError, match="fix no pose"):
        prior_posterior(JJ, np.eye(4), 1.0)
    JJ = np.ones((10, 10))  # rank one: positive diagonal, not positive definite
    with pytest.raises(InputError, match="not positive definite"):
        prior_posterior(JJ, np.eye(4) * 1e-30, 1.0)
