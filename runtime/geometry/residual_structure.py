"""How much of a frame's residual under a pinhole camera is smooth structure that neither a
change of that camera's K and pose nor independent corner noise make.

With r = x - pi(K, pose) the residuals (px) at a pose fitted under K, two linear
least-squares fits of r in the tangent space of the camera (``cv2.projectPoints``' Jacobian
in the pose's 6 and fx, fy, cx, cy: what a change of K or pose, OIS among it, would explain):

- base: that Jacobian J alone;
- smooth: J and a smooth field, per image axis the cubic polynomials of the point's
  normalised camera coordinates (u, v) = (pi - c) / f at the projection (20 columns): a sheet
  that is not flat, a lens K leaves out, a corner bias that varies across the image.

With N points, RSS_b and RSS_s the two fits' residual sums of squares and q the columns the
field adds (after rank), the noise variance is s^2 = RSS_s / (2N - rank) and
``amplitude_px`` = sqrt(max(RSS_b - RSS_s - q s^2, 0) / N): the structure's RMS per point
(px) beyond what q more columns fit out of pure noise; ``ratio`` = ((RSS_b - RSS_s) / q) / s^2,
the F statistic (about 1 under independent noise). ``radial_share``: the share of RSS_b -
RSS_s that two radial columns (u, v) r^2 and (u, v) r^4 alone explain, r^2 = u^2 + v^2: the
shape of the radial lens error OpenCV's k1, k2 model.

Points are projected, not observed, in the field's columns: the observed pixels lie in the
span of J's focal and principal-point columns plus the residual itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# Points a frame needs for the test: twice the columns of the smooth fit, so that its noise
# estimate has as many degrees of freedom as the fit has columns.
MIN_STRUCTURE_POINTS = 30
# Points the test reads at most, and the Gram matrix's ridge (its columns have unit norm).
STRUCTURE_POINTS = 80
RIDGE = 1e-9


@dataclass(frozen=True)
class ResidualStructure:
    """amplitude_px: the RMS (px per point) of the smooth structure beyond noise; ratio: its
    F statistic; radial_share in [0, 1]: the share of it that a radial lens error explains;
    noise_px: the RMS (px per axis) of what is left."""

    amplitude_px: float
    ratio: float
    radial_share: float
    noise_px: float


def residual_structure(
    points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray
) -> ResidualStructure:
    """The structure of one frame's residuals: points_2d (N, 2) px (pinhole, undistorted),
    points_3d (N, 3) mm in {W}, K (3, 3) px and the pose rvec, tvec {W}->{C} fitted under it;
    N >= MIN_STRUCTURE_POINTS; frames of more than STRUCTURE_POINTS points are read at that many,
    evenly spread over their order (the test's cost stays ~40 us)."""
    n = len(points_2d)
    if n > STRUCTURE_POINTS:
        step = -(-n // STRUCTURE_POINTS)
        points_2d, points_3d = points_2d[::step], np.ascontiguousarray(points_3d[::step])
        n = len(points_2d)
    projected, jacobian = cv2.projectPoints(points_3d, rvec, tvec, K, None)
    projected = projected.reshape(-1, 2)
    r = (points_2d - projected).reshape(-1)
    u = (projected[:, 0] - K[0, 2]) / K[0, 0]
    v = (projected[:, 1] - K[1, 2]) / K[1, 1]
    # The columns [J (10), radial (2), smooth (20)], rows x0, y0, x1, ...: the radial displacement
    # (u, v) r^2 and (u, v) r^4, then per image axis the cubic polynomials of (u, v).
    A = np.zeros((2 * n, 32))
    A[:, :10] = jacobian[:, :10]
    r2 = u * u + v * v
    r4 = r2 * r2
    A[0::2, 10:12] = np.stack([u * r2, u * r4], 1)
    A[1::2, 10:12] = np.stack([v * r2, v * r4], 1)
    uu, uv, vv = u * u, u * v, v * v
    poly = np.stack([np.ones_like(u), u, v, uu, uv, vv, uu * u, uu * v, u * vv, vv * v], 1)
    A[0::2, 12:22] = poly
    A[1::2, 22:32] = poly
    # Nested fits from one Cholesky factor L of the Gram matrix (columns scaled to unit norm, a
    # ridge of RIDGE for the ranks a planar frame's J lacks): the first k columns leave
    # r.r - sum_{i<k} y_i^2 of r, y = L^-1 A^T r.
    gram, b = A.T @ A, A.T @ r
    scale = 1.0 / np.sqrt(np.maximum(gram.diagonal(), 1e-300))
    gram *= np.outer(scale, scale)
    gram[np.diag_indices_from(gram)] += RIDGE
    L = np.linalg.cholesky(gram)
    y2 = np.linalg.solve(L, b * scale) ** 2
    # A column that adds a direction has a Cholesky pivot well above the ridge.
    adds = L.diagonal() ** 2 > 1e3 * RIDGE
    base, radial = float(y2[:10].sum()), float(y2[10:12].sum())
    explained = float(y2[10:].sum())
    q = max(int(np.count_nonzero(adds[10:])), 1)
    rank = int(np.count_nonzero(adds))
    noise_var = max(float(r @ r) - base - explained, 0.0) / max(r.size - rank, 1)
    return ResidualStructure(
        amplitude_px=float(np.sqrt(max(explained - q * noise_var, 0.0) / n)),
        ratio=explained / q / noise_var if noise_var > 0 else float("inf"),
        radial_share=min(radial / explained, 1.0) if explained > 0 else 0.0,
        noise_px=float(np.sqrt(noise_var)),
    )
