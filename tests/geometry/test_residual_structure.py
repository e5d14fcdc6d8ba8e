"""``geometry.residual_structure``: noise and a change of K or pose are not structure; a smooth field
the camera cannot make is, at about its size; a radial one is told apart."""

from __future__ import annotations

import numpy as np

from dimenet.runtime.geometry import k_matrix, project, residual_structure, solve_pnp_start

K = k_matrix(np.array([3000.0, 3000.0, 2000.0, 1500.0]))


def _scene(rng, n=300):
    """Points on two tilted planes ~500 mm away and a pose seeing them."""
    xy = rng.uniform(-150, 150, (n, 2))
    z = np.where(np.arange(n) % 2 == 0, 0.0, 0.4 * xy[:, 0])
    X = np.column_stack([xy, z])
    rvec, tvec = np.array([0.2, -0.1, 0.05]), np.array([10.0, -20.0, 520.0])
    return X, project(X, K, rvec, tvec)


def _structure(x, X, K_fit=K):
    return residual_structure(x, X, K_fit, *solve_pnp_start(x, X, K_fit))


def test_noise_alone_is_no_structure():
    rng = np.random.default_rng(0)
    X, x = _scene(rng)
    s = _structure(x + rng.normal(0, 0.5, x.shape), X)
    assert s.amplitude_px < 0.1 and s.ratio < 3 and abs(s.noise_px - 0.5) < 0.1


def test_an_ois_shift_of_the_principal_point_is_no_structure():
    rng = np.random.default_rng(1)
    X, _ = _scene(rng)
    shifted = k_matrix(np.array([3000.0, 3000.0, 2030.0, 1480.0]))
    x = project(X, shifted, np.array([0.2, -0.1, 0.05]), np.array([10.0, -20.0, 520.0]))
    s = _structure(x + rng.normal(0, 0.3, x.shape), X)  # read under K: K and pose absorb the shift
    assert s.amplitude_px < 0.1 and s.ratio < 3


def test_a_smooth_field_is_structure_of_about_its_size():
    rng = np.random.default_rng(2)
    X, x = _scene(rng)
    u, v = (x[:, 0] - 2000) / 3000, (x[:, 1] - 1500) / 3000
    field = 6.0 * np.column_stack([u * u * v, (u * u - v * v) * u]) / np.abs(u).max() ** 3
    s = _structure(x + field + rng.normal(0, 0.5, x.shape), X)
    rms = np.sqrt((field**2).sum(1).mean())
    assert s.ratio > 10 and 0.2 * rms < s.amplitude_px <= 1.05 * rms
    assert s.radial_share < 0.5


def test_a_radial_lens_error_is_told_apart():
    rng = np.random.default_rng(3)
    X, x = _scene(rng)
    u, v = (x[:, 0] - 2000) / 3000, (x[:, 1] - 1500) / 3000
    r2 = u * u + v * v
    radial = 3000 * np.column_stack([u, v]) * (-0.2 * r2)[:, None]
    s = _structure(x + radial + rng.normal(0, 0.3, x.shape), X)
    assert s.ratio > 10 and s.amplitude_px > 0.3 and s.radial_share > 0.5
