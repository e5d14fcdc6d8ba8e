"""One lens under many K: the bundle adjustment of per-frame K and pose with one shared distortion.

Under OIS every frame has its own pinhole K while the lens, and so its distortion, stays one.
A frame's image point is D(pi(K_b, R_b X + t_b)), D the lens's distortion (OpenCV's model,
``geometry.distortion``) about a fixed K_lens (the camera's K_c). Unknowns: per frame (rotation
as a left perturbation, translation mm, fx, fy, cx, cy px), as in the LM core
(``least_squares``), whose projection Jacobian is reused; and the n distortion coefficients,
shared. The frames couple only through the lens, so each LM step solves the 10 x 10 frame blocks
and a Schur complement over the n coefficients instead of the whole (10 B + n) system. One
damping for all (the lens couples every frame's cost), by the LM core's rule (``least_squares.damped``,
``next_damping``); a step is kept when the total cost falls.
Cost: sum_i w_i ||D(pi(K_b, X_i)) - x_i||^2 (px^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dimenet.runtime.geometry.distortion import distort_points_with_jacobians
from dimenet.runtime.geometry.least_squares import DAMPING_MAX, DAMPING_START, damped, jacobian, next_damping, residuals
from dimenet.runtime.geometry.projection import k_matrix, k_params
from dimenet.runtime.geometry.rotation import matrix_to_rvec, rvec_to_matrix


@dataclass(frozen=True)
class LensBundleResult:
    """K (B, 3, 3) px and pose rvec, tvec (B, 3) {W}->{C} of every frame's pinhole camera;
    dist_coeffs (n,) about the given K_lens; cost (B,) px^2 per frame in the distorted image."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    dist_coeffs: np.ndarray
    cost: np.ndarray
    iterations: int


def _distorted(p2, p3, sqrt_w, kp, R, t, K_lens, dist):
    """Weighted residuals (B, N, 2) in the distorted image and what the Jacobians need."""
    offset, Xc, z, xn, yn = residuals(p2, p3, np.ones_like(sqrt_w), kp, R, t)  # pi(K, X_C) - x, unweighted
    pinhole = offset + p2
    image, by_pixel, by_coeff = distort_points_with_jacobians(pinhole.reshape(-1, 2), K_lens, dist)
    B, N = z.shape
    r = (image.reshape(B, N, 2) - p2) * sqrt_w[..., None]
    return r, (Xc, z, xn, yn, by_pixel.reshape(B, N, 2, 2), by_coeff.reshape(B, N, 2, -1))


def fit_lens_bundle(
    points_2d,
    points_3d,
    weights,
    K,
    rvec,
    tvec,
    K_lens,
    dist_coeffs,
    *,
    max_iterations: int = 100,
    tolerance: float = 1e-12,
) -> LensBundleResult:
    """Minimise the distorted reprojection error of B frames over their K and pose and one lens.

    points_2d (B, N, 2) px as the image holds them; points_3d (B, N, 3) mm {W}; weights (B, N)
    >= 0; K (B, 3, 3) px and rvec, tvec (B, 3) the start (e.g. each frame's pinhole K*);
    K_lens (3, 3) px the fixed K the distortion is stated about; dist_coeffs (n,) the lens's start
    (OpenCV's model, n = 4, 5 or 8; zeros: none). Stops when the relative cost decrease falls
    below ``tolerance``.
    """
    w = np.asarray(weights, dtype=np.float64)
    use = w > 0
    sqrt_w = np.sqrt(np.where(use, w, 0.0))
    p2 = np.where(use[..., None], points_2d, 0.0)
    p3 = np.where(use[..., None], points_3d, 0.0)
    kp, R, t = k_params(K).copy(), rvec_to_matrix(rvec), np.array(tvec, dtype=np.float64)
    dist = np.array(dist_coeffs, dtype=np.float64)
    B = len(p2)
    lam = DAMPING_START
    r, parts = _distorted(p2, p3, sqrt_w, kp, R, t, K_lens, dist)
    cost = (r**2).sum()
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 (it is the count reported)
        Xc, z, xn, yn, by_pixel, by_coeff = parts
        J_frame = (by_pixel @ jacobian(sqrt_w, kp, Xc, t, z, xn, yn, True)).reshape(B, -1, 10)
        J_lens = (by_coeff * sqrt_w[..., None, None]).reshape(B, -1, len(dist))
        res = r.reshape(B, -1)
        U = np.einsum("bki,bkj->bij", J_frame, J_frame)
        W = np.einsum("bki,bkj->bij", J_frame, J_lens)
        V = np.einsum("bki,bkj->ij", J_lens, J_lens)
        g_frame = np.einsum("bki,bk->bi", J_frame, res)
        g_lens = np.einsum("bki,bk->i", J_lens, res)
        U, V = damped(U, lam), damped(V, lam)
        # [U W; W^T V] [d_frame; d_lens] = -[g_frame; g_lens], the frames eliminated first.
        U_inv_W = np.linalg.solve(U, W)
        U_inv_g = np.linalg.solve(U, g_frame[..., None])[..., 0]
        S = V - np.einsum("bki,bkj->ij", W, U_inv_W)
        d_lens = np.linalg.solve(S, -g_lens + np.einsum("bki,bk->i", W, U_inv_g))
        d_frame = -U_inv_g - U_inv_W @ d_lens
        R_new = rvec_to_matrix(d_frame[:, :3]) @ R
        t_new, kp_new, dist_new = t + d_frame[:, 3:6], kp + d_frame[:, 6:10], dist + d_lens
        r_new, parts_new = _distorted(p2, p3, sqrt_w, kp_new, R_new, t_new, K_lens, dist_new)
        cost_new = (r_new**2).sum()
        better = cost_new < cost
        if better:
            gain = (cost - cost_new) / max(cost, 1e-300)
            R, t, kp, dist, r, parts, cost = R_new, t_new, kp_new, dist_new, r_new, parts_new, cost_new
        lam = float(next_damping(lam, better))
        if (better and gain < tolerance) or lam > DAMPING_MAX:
            break
    return LensBundleResult(
        K=k_matrix(kp), rvec=matrix_to_rvec(R), tvec=t, dist_coeffs=dist, cost=(r**2).sum((1, 2)), iterations=it
    )
