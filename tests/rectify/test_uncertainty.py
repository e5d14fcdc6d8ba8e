"""The uncertainty model: older spec versions, the point-cloud thickness statistic, the posterior scale."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import constant_uncertainty, point_thickness

from dimenet.runtime.geometry import covariance_invariants_batch
from dimenet.runtime.rectify.uncertainty import NOISE_SCALE_PX, T_FLOOR, Uncertainty, input_statistics


def test_a_spec_1_1_uncertainty_reads_the_first_three_statistics():
    coef = np.array([[1.0, -0.5, 0.0, 0.3]] * 4)
    old = Uncertainty.from_dict(
        {
            "parameters": ["fx", "fy", "cx", "cy"],
            "statistics": ["1", "log_points", "log_cells", "log_pmd"],
            "coef": coef.tolist(),
            "correlation": np.eye(4).tolist(),
        },
        48,
    )
    stats = np.log([[100, 20, 2.5, 1e-6], [100, 20, 2.5, 0.3]])  # the thickness does not matter to it
    np.testing.assert_allclose(old.sigma(stats), np.exp(1.0 - 0.5 * np.log(100) + 0.3 * np.log(2.5)) * np.ones((2, 4)))
    np.testing.assert_allclose(old.frame_covariance(100, 20, 2.5, 0.3), old.covariance(stats)[1], rtol=1e-12)


def test_point_thickness_hand_computed_cases():
    axes = np.vstack([np.eye(3), -np.eye(3)])  # covariance I/3: an isotropic cloud
    assert point_thickness(axes) == pytest.approx(1 / 3)
    box = axes * [2.0, 1.0, 0.1]  # covariance diag(4, 1, 0.01) / 3: det tr / e2^2 = 0.04 * 5.01 / 4.05^2
    assert point_thickness(box * 250.0) == pytest.approx(0.04 * 5.01 / 4.05**2)  # scale free
    rng = np.random.default_rng(0)
    plane = np.c_[rng.normal(size=(50, 2)), np.zeros(50)] @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    assert point_thickness(np.ascontiguousarray(plane)) < 1e-12
    assert point_thickness(np.outer(rng.normal(size=20), [1.0, 2.0, 3.0])) == 0.0  # a line
    mask = np.array([[True] * 6, [True] * 3 + [False] * 3])
    stats = input_statistics(
        np.ones((2, 6)), mask.sum(1), np.ones(2), covariance_invariants_batch(np.stack([axes, box]), mask), 2
    )
    assert stats[0, 3] == pytest.approx(np.log(1 / 3)) and stats[1, 3] == np.log(T_FLOOR)  # 3 points: a plane


def test_posterior_scale_hand_computed():
    u = replace(constant_uncertainty(1.0), data_correlation=np.array([0.0, 0.2, 0.5, 1.0]))
    # s = s0: half the correlation applies (w = 1/2); r = 1/2: sqrt(r (1 - r)) = 1/2.
    np.testing.assert_allclose(u.posterior_scale([0.5] * 4, NOISE_SCALE_PX), np.sqrt([1.0, 1.1, 1.25, 1.5]), rtol=1e-12)
    # A posterior equal to the prior (r = 1) or set by the data alone (r = 0) is not widened,
    # nor is a noise-free frame.
    assert u.posterior_scale([1.0, 0.0, 1.0, 0.0], 5.0) == [1.0] * 4
    assert u.posterior_scale([0.5] * 4, 0.0) == [1.0] * 4


def test_map_covariance_adds_the_data_bias_share_of_the_network_covariance():
    network = np.array([[4.0, 1.0, 0, 0], [1.0, 9.0, 0, 0], [0, 0, 16.0, 2.0], [0, 0, 2.0, 25.0]])
    posterior = np.diag([1.0, 2.0, 3.0, 4.0])
    plain = constant_uncertainty(1.0)
    np.testing.assert_array_equal(plain.map_covariance(posterior, network, 3.0), posterior)  # spec < 1.10: as it was
    b = np.array([0.0, 0.5, 1.0, 2.0])
    biased = replace(plain, data_bias=b)
    np.testing.assert_allclose(biased.map_covariance(posterior, network, 3.0), posterior + network * np.outer(b, b))
    # with a correlation too: the posterior is widened first, then the bias is added
    both = replace(biased, data_correlation=np.full(4, 0.5))
    scale = np.array(both.posterior_scale((posterior.diagonal() / network.diagonal()).tolist(), 3.0))
    np.testing.assert_allclose(
        both.map_covariance(posterior, network, 3.0), posterior * np.outer(scale, scale) + network * np.outer(b, b)
    )
    assert Uncertainty.from_dict(biased.to_dict(), 48).data_bias.tolist() == b.tolist()
    assert "data_bias" not in plain.to_dict()  # a model without it writes the 1.9 object
    with pytest.raises(ValueError, match=r"data_bias must be 4 values in \[0, 3\]"):
        replace(plain, data_bias=np.array([0.0, 0.0, 3.5, 0.0]))
