"""How points spread: covariance invariants of point sets, and whether they span 3D."""

from __future__ import annotations

import numpy as np

# Below this smallest over largest singular value of the centred 3D points, they count as one
# plane: K is not observable from one view of them.
PLANAR_RATIO = 0.05
# What a rig view must span to be kept (simulated, rendered or identified): twice that, so
# every kept view calibrates with margin.
RIG_VIEW_RATIO = 0.1
# Largest |3D coordinate| dimenet accepts, in the points' unit (1e12 mm is 10^6 km): beyond it
# the covariance invariants of point sets overflow float64.
MAX_COORDINATE = 1e12
# The covariance's entries covariance_invariants sums, by dimension: the (row, column) pairs of its upper triangle.
PAIRS = {2: ([0, 0, 1], [0, 1, 1]), 3: ([0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2])}


def covariance_invariants(points: np.ndarray) -> tuple[float, float, float]:
    """Trace, sum of principal 2x2 minors and determinant of the sample covariance (1 / n) of one
    frame's (N, D) float64 points, D = 2 or 3 (units^2, ^4, ^(2D)), every sum in point order (np.cumsum's
    last row: the mean, then the centred products), which the compiled core's ``dimenet_frame_checks``
    follows to the bit for D = 3."""
    n, pairs = len(points), PAIRS[points.shape[1]]
    with np.errstate(over="ignore", invalid="ignore"):  # huge points overflow to inf or NaN: not clearly spread
        centred = points - np.cumsum(points, axis=0)[-1] / n
        covariance = (np.cumsum(centred[:, pairs[0]] * centred[:, pairs[1]], axis=0)[-1] / n).tolist()
    if points.shape[1] == 2:
        a, b, d = covariance
        return a + d, a * d - b * b, a * d - b * b
    a, b, c, d, e, f = covariance
    det = (a * (d * f - e * e) - b * (b * f - e * c)) + c * (b * e - d * c)
    return (a + d) + f, ((a * d - b * b) + (a * f - c * c)) + (d * f - e * e), det


def covariance_invariants_batch(points: np.ndarray, mask) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``covariance_invariants`` of B frames at once (numpy): points (B, P, D) float64, D = 2 or
    3, mask (B, P) bool of the points to use (>= 1 per frame) or None (all) -> trace, sum of
    principal 2x2 minors and determinant, (B,) each."""
    T = np.ascontiguousarray(np.swapaxes(points, 1, 2))  # (B, D, P), coordinate-major
    if mask is not None:
        np.copyto(T, 0.0, where=~mask[:, None, :])
    n = np.full(len(T), T.shape[2], np.float64) if mask is None else mask.sum(1).astype(np.float64)
    T -= (T.sum(-1) / n[:, None])[:, :, None]
    if mask is not None:
        np.copyto(T, 0.0, where=~mask[:, None, :])
    C = np.matmul(T, np.swapaxes(T, 1, 2)) / n[:, None, None]
    D = points.shape[-1]
    minors = sum(C[:, i, i] * C[:, j, j] - C[:, i, j] * C[:, j, i] for i in range(D) for j in range(i + 1, D))
    return np.trace(C, axis1=1, axis2=2), minors, np.linalg.det(C)


def spans_3d(points_mm: np.ndarray, min_ratio: float = PLANAR_RATIO) -> bool:
    """Whether (N, 3) points are far enough from one plane: the smallest singular value of the
    centred points at least ``min_ratio`` times the largest (scale free). The default is where
    a one-view K (DLT) fit refuses; rig views ask for RIG_VIEW_RATIO."""
    sv = np.linalg.svd(points_mm - points_mm.mean(0), compute_uv=False)
    return bool(sv[2] >= min_ratio * sv[0])
