"""Small synthetic scenes for unit tests (no simulator needed)."""

from __future__ import annotations

import numpy as np

from dimenet.runtime import geometry as g

K_TEST = np.array([[3000.0, 0.0, 2016.0], [0.0, 3010.0, 1512.0], [0.0, 0.0, 1.0]])


def random_frames(rng, frames=4, points=60, noise_px=0.0, K=K_TEST, planar=False):
    """Non-planar point clouds ~0.4-0.9 m in front of a camera; returns p2 (px), p3 (mm), K, rvec, tvec."""
    X = rng.uniform(-150, 150, (frames, points, 3))
    if planar:
        X[..., 2] = 0.0
    K = np.broadcast_to(K, (frames, 3, 3)).copy()
    rvec = rng.normal(0, 0.2, (frames, 3))
    tvec = np.c_[rng.normal(0, 30, (frames, 2)), rng.uniform(400, 900, frames)]
    x = g.project(X, K, rvec, tvec) + rng.normal(0, noise_px, (frames, points, 2))
    return x, X, K, rvec, tvec
