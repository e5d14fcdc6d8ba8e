"""MAP rectification of one frame: K and pose from the frame's own points and the network's prior.

Minimises over (rvec, tvec, k = (fx, fy, cx, cy))

    sum_i ||pi(K, R X_i + t) - x_i||^2 / s^2  +  (k - k_net)^T Sigma^-1 (k - k_net)

where k_net, Sigma (4x4, px^2) are the network's Delta K mean and covariance (added to K_c)
and s^2 (px^2) the frame's 2D noise variance, estimated from its residuals under k_net:
s^2 = RSS / (2N - 6), floored at NOISE_FLOOR_PX^2. ITERATIONS Gauss-Newton steps from the
DIME-Net solution with OpenCV's analytic projection Jacobian (cv2.projectPoints); a step
that does not lower the cost ends the fit. The posterior covariance of k is the K block of
the inverse Gauss-Newton Hessian at the last linearisation.

One frame's few Gauss-Newton steps on a well-conditioned 10x10 system: the prior keeps K
observable even from one planar view, where the data alone cannot fix it.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .errors import InputError
from .geometry import frame_k_matrix, frame_residuals, solve_pnp_start

# Gauss-Newton steps. From the DIME-Net start one step lands on the optimum: on the galaxy-s8
# test frames rho agrees to 0.01 point with 8 steps (rig, 64 points, natural, planar).
ITERATIONS = 1
NOISE_FLOOR_PX = 0.1


@dataclass(frozen=True)
class MapFit:
    """k (4,) px (fx, fy, cx, cy); rvec (3,) rad, tvec (3,) mm {W}->{C}; k_cov (4, 4) px^2 the
    posterior covariance; residuals (N, 2) px at the result; noise_px the estimated s; steps
    the Gauss-Newton steps taken (a step that would raise the cost ends the fit)."""

    k: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    k_cov: np.ndarray
    residuals: np.ndarray
    noise_px: float
    steps: int


def map_fit(points_2d: np.ndarray, points_3d: np.ndarray, k_net: np.ndarray, cov_net: np.ndarray,
            rvec: np.ndarray, tvec: np.ndarray, *, iterations: int = ITERATIONS) -> MapFit:
    """MAP (K, pose) of one frame: points_2d (N, 2) px, points_3d (N, 3) mm in {W}, float64;
    k_net (4,) px the network's K; cov_net (4, 4) px^2 its covariance; rvec, tvec the pose
    {W}->{C} under k_net (the start); iterations >= 1 Gauss-Newton steps at most."""
    precision = cv2.invert(cov_net, flags=cv2.DECOMP_CHOLESKY)[1]
    k = np.array(k_net, dtype=np.float64)
    rvec, tvec = np.array(rvec, dtype=np.float64).ravel(), np.array(tvec, dtype=np.float64).ravel()
    x, J = cv2.projectPoints(points_3d, rvec, tvec, frame_k_matrix(k), None)
    r = x.reshape(-1) - points_2d.reshape(-1)
    weight = 1.0 / max(float(r @ r) / max(r.size - 6, 1), NOISE_FLOOR_PX**2)
    cost, residuals, steps = weight * float(r @ r), r.reshape(-1, 2), 0
    for it in range(iterations):
        if it:
            x, J = cv2.projectPoints(points_3d, rvec, tvec, frame_k_matrix(k), None)
            r = x.reshape(-1) - points_2d.reshape(-1)
        J = J[:, :10]  # d(u, v)/d(rvec, tvec, fx, fy, cx, cy), point-interleaved rows
        H = weight * (J.T @ J)
        H[6:, 6:] += precision
        g = weight * (J.T @ r)
        g[6:] += precision @ (k - k_net)
        step = cv2.solve(H, g.reshape(10, 1), flags=cv2.DECOMP_CHOLESKY)[1].ravel()
        k_new, rvec_new, tvec_new = k - step[6:], rvec - step[:3], tvec - step[3:6]
        res = frame_residuals(points_2d, points_3d, frame_k_matrix(k_new), rvec_new, tvec_new)
        d = k_new - k_net
        cost_new = weight * float(np.vdot(res, res)) + float(d @ precision @ d)
        if not cost_new <= cost:
            break
        k, rvec, tvec, cost, residuals, steps = k_new, rvec_new, tvec_new, cost_new, res, steps + 1
    k_cov = cv2.invert(H, flags=cv2.DECOMP_CHOLESKY)[1][6:, 6:]
    return MapFit(k=k, rvec=rvec, tvec=tvec, k_cov=(k_cov + k_cov.T) / 2, residuals=residuals,
                  noise_px=float(np.sqrt(1.0 / weight)), steps=steps)


def map_rectify(points_2d: np.ndarray, points_3d: np.ndarray, k_net: np.ndarray, cov_net: np.ndarray,
                k_bounds: np.ndarray, pose=None) -> tuple[MapFit | None, str | None]:
    """``map_fit`` from the pose under k_net (``pose`` (rvec, tvec), else SQPnP here), checked:
    (fit, None), or (None, why) when there is no start pose or the MAP K is not finite or
    outside ``k_bounds`` (4, 2) px; the caller then keeps the DIME-Net K."""
    if pose is None:
        try:
            pose = solve_pnp_start(points_2d, points_3d, frame_k_matrix(k_net))
        except InputError:
            return None, "no pose under the network's K"
    result = map_fit(points_2d, points_3d, k_net, cov_net, *pose)
    if not (np.all(np.isfinite(result.k)) and np.all((result.k >= k_bounds[:, 0]) & (result.k <= k_bounds[:, 1]))):
        return None, "the MAP K is implausible (outside the model's K_bounds)"
    return result, None
