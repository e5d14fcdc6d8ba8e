"""MAP rectification of one frame: K and pose from the frame's own points and the network's prior.

Minimises over (rvec, tvec, k = (fx, fy, cx, cy))

    sum_i ||pi(K, R X_i + t) - x_i||^2 / s^2  +  (k - k_net)^T Sigma^-1 (k - k_net)

where k_net, Sigma (4x4, px^2) are the network's Delta K mean and covariance (added to K_c)
and s^2 (px^2) the frame's 2D noise variance: s^2 = RSS / (2N - 10) of the linearised MAP
residuals (first weighted by the start's own residuals), floored at NOISE_FLOOR_PX^2.
ITERATIONS Gauss-Newton steps from k_net and the C0 pose (the PnP pose under K_c) with the
analytic normal equations (``geometry.frame_normal_equations``, the pose perturbed on the
left); a step that does not lower the cost ends the fit. The posterior covariance of k is
the K block of the inverse Gauss-Newton Hessian at the last linearisation.

One frame's few Gauss-Newton steps on a well-conditioned 10x10 system: the prior keeps K
observable even from one planar view, where the data alone cannot fix it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from .errors import InputError
from .geometry import (camera_xy_inverse_depth, frame_k_matrix, frame_normal_equations, frame_residuals, left_update,
                       solve_pnp_start)

# Gauss-Newton steps. From k_net and the C0 pose one step lands near the optimum: on galaxy-s8
# test frames rho agrees with 8 steps to within 0.4 point (rig, 64 points, natural, planar).
ITERATIONS = 1
NOISE_FLOOR_PX = 0.1
# The start pose (C0, under K_c) is not the optimum under k_net, so its residuals overstate the
# noise: s^2 is re-estimated this many times from the linearised MAP residuals (2N - 10 dof).
# galaxy-s8 seed-1 test rho, passes 0 / 1 / 2: natural 72.8 / 89.7 / 89.8, planar 49.8 / 87.5 / 89.0.
NOISE_PASSES = 1


@dataclass(frozen=True)
class MapFit:
    """k (4,) px (fx, fy, cx, cy); rvec (3,) rad, tvec (3,) mm {W}->{C}; k_cov (4, 4) px^2 the
    posterior covariance; residuals (N, 2) px at the result; steps: the Gauss-Newton steps
    taken (0: the first step would have raised the cost, the result is the start)."""

    k: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    k_cov: np.ndarray
    residuals: np.ndarray
    steps: int


def map_fit(points_2d: np.ndarray, points_3d: np.ndarray, k_net: np.ndarray, cov_net: np.ndarray,
            rvec: np.ndarray, tvec: np.ndarray, *, iterations: int = ITERATIONS,
            start_points: Optional[np.ndarray] = None) -> MapFit:
    """MAP (K, pose) of one frame: points_2d (N, 2) px, points_3d (N, 3) mm in {W}, float64;
    k_net (4,) px the network's K; cov_net (4, 4) px^2 its covariance; rvec, tvec a start pose
    {W}->{C} near the optimum (e.g. the C0 pose under K_c); iterations >= 1 Gauss-Newton steps
    at most; start_points (3, N) the points at the start pose as X, Y (mm), 1/Z (1/mm), when
    the caller has them (the grid feature's point rows 2-4 at the C0 pose), else computed here."""
    precision = cv2.invert(cov_net, flags=cv2.DECOMP_CHOLESKY)[1]
    k_net = np.asarray(k_net, dtype=np.float64)
    k, rvec, tvec = k_net, np.asarray(rvec, dtype=np.float64).ravel(), np.asarray(tvec, dtype=np.float64).ravel()
    if start_points is None:
        start_points = camera_xy_inverse_depth(points_3d, rvec, tvec)
    JJ, Jr, rss, r = frame_normal_equations(start_points, points_2d, k)
    weight = _noise_weight(rss, r.size - 6)
    for _ in range(NOISE_PASSES):
        # |r - J^T step|^2 of the linearised step, from the 10x10 normal equations.
        step = _posterior(JJ, precision, weight) @ Jr * weight
        weight = _noise_weight(rss - 2.0 * float(step @ Jr) + float(step @ JJ @ step), r.size - 10)
    cov = _posterior(JJ, precision, weight)
    cost, residuals, steps = weight * rss, None, 0
    for it in range(iterations):
        g = Jr * weight
        if it:  # the prior's gradient, zero at the start k = k_net
            g[6:] += precision @ (k - k_net)
        step = cov @ g
        step *= -1.0
        k_new = k + step[6:]
        rvec_new, tvec_new = left_update(rvec, tvec, step[:3], step[3:6])
        res = frame_residuals(points_2d, points_3d, frame_k_matrix(k_new), rvec_new, tvec_new)
        d = k_new - k_net
        cost_new = weight * float(np.vdot(res, res)) + float(d @ precision @ d)
        if not cost_new <= cost:
            break
        k, rvec, tvec, cost, residuals, steps = k_new, rvec_new, tvec_new, cost_new, res, steps + 1
        if it + 1 < iterations:
            JJ, Jr, _, r = frame_normal_equations(camera_xy_inverse_depth(points_3d, rvec, tvec), points_2d, k)
            cov = _posterior(JJ, precision, weight)
    if residuals is None:
        residuals = np.ascontiguousarray(r.T)
    k_cov = cov[6:, 6:]
    return MapFit(k=k, rvec=rvec, tvec=tvec, k_cov=(k_cov + k_cov.T) / 2, residuals=residuals, steps=steps)


def _noise_weight(rss: float, dof: int) -> float:
    """1 / s^2 (px^-2) from a residual sum of squares rss (px^2) with dof degrees of freedom."""
    return 1.0 / max(rss / max(dof, 1), NOISE_FLOOR_PX**2)


def _posterior(JJ: np.ndarray, precision: np.ndarray, weight: float) -> np.ndarray:
    """The inverse of the 10x10 Gauss-Newton Hessian of the MAP cost, weight J J^T plus the prior
    on K: the step is its product with the gradient, its K block the posterior covariance."""
    H = JJ * weight
    H[6:, 6:] += precision
    return cv2.invert(H, flags=cv2.DECOMP_CHOLESKY)[1]


def map_rectify(points_2d: np.ndarray, points_3d: np.ndarray, k_net: np.ndarray, cov_net: np.ndarray,
                k_bounds: np.ndarray, K_c: np.ndarray, pose=None,
                start_points: Optional[np.ndarray] = None) -> tuple[MapFit | None, str | None]:
    """``map_fit`` from the C0 pose (``pose`` (rvec, tvec) under K_c (3, 3), else SQPnP here;
    ``start_points`` its X, Y, 1/Z rows at that pose, see ``map_fit``), checked: (fit, None),
    or (None, why) when there is no start pose, no step lowered the cost (the start pose is
    K_c's, not k_net's optimum, so the caller's own PnP under k_net is better) or the MAP K is
    not finite or outside ``k_bounds`` (4, 2) px; the caller then keeps the DIME-Net K."""
    if pose is None:
        try:
            pose = solve_pnp_start(points_2d, points_3d, K_c)
        except InputError:
            return None, "no C0 pose under K_c"
    result = map_fit(points_2d, points_3d, k_net, cov_net, *pose, start_points=start_points)
    if result.steps == 0:
        return None, "the MAP step did not lower the cost"
    # Plain floats: a NaN fails every comparison, so this also refuses a non-finite K.
    if not all(low <= v <= high for v, (low, high) in zip(result.k.tolist(), k_bounds.tolist())):
        return None, "the MAP K is implausible (outside the model's K_bounds)"
    return result, None
