"""The moments encoder (``FeatureSpec.moments``, spec >= 1.11; not the paper's): the frame's point set pooled
whatever its layout.

The mean over its points of every product of two of [1, a, b, ab, a^2, b^2, z, a z, b z, s dx, s dy], a = X/Z and
b = Y/Z in {C0}, z the point's inverse depth over the frame's mean inverse depth and s the PMD's scale (the upper
triangle in row order, less the two that are always 1): how the points spread over the image and in depth, and how
the PMD varies over them. They are the normal equations' own statistics (``geometry.monomial_gram``). Compiled: the
last ``size`` values of ``dimenet_frame_features``' output (runtime/native/dimenet_features.c).
"""

from __future__ import annotations

import numpy as np

NAME = "moments"


# The upper triangle of the 11 x 11 monomial Gram, less [1 * 1] and [1 * z] (both 1).
def _moment_index() -> np.ndarray:
    rows, cols = np.triu_indices(11)
    keep = ~((rows == 0) & ((cols == 0) | (cols == 6)))
    return np.ravel_multi_index((rows[keep], cols[keep]), (11, 11))


MOMENT_INDEX = _moment_index()  # into the raveled Gram
MOMENT_SIZE = len(MOMENT_INDEX)


def size(spec) -> int:
    return MOMENT_SIZE if spec.moments else 0


def encode(G: np.ndarray, n: int, K_c, spec) -> np.ndarray:
    """(MOMENT_SIZE,) the moments of one frame of n points from its monomial Gram G (11, 11): each monomial's
    scale s (1, z's n / sum(1/Z), the PMD's scale), then s_i s_j G_ij / n (K_c unused)."""
    pmd_scale = spec.scale["dx"]
    z_scale = n / G[0, 6] if G[0, 6] > 0 else 1.0
    s = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, z_scale, z_scale, z_scale, pmd_scale, pmd_scale])
    return (G * np.outer(s, s / n)).ravel()[MOMENT_INDEX]
