"""One frame's MAP Gauss-Newton steps over (pose, K) with a Gaussian prior on K: mode map's fit
(``rectify.map_fit``), and the reference of the compiled core's one step (``dimenet_map_step``,
runtime/native/dimenet_map.c), which equals it to the bit."""

from __future__ import annotations

import cv2
import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry.normal_equations import (
    frame_normal_equations,
    matvec,
    posterior_step,
    prior_posterior,
    prior_step,
)
from dimenet.runtime.geometry.projection import (
    camera_rows,
    camera_xy_inverse_depth,
    frame_mean_norm,
    k_matrix,
    pinhole_residuals,
)
from dimenet.runtime.geometry.rotation import left_update, rotated


def principal_point_turn(K_from: np.ndarray, k_to: np.ndarray) -> np.ndarray:
    """The rotation (3,) rad that turns a pose {W}->{C} so that under k_to (4,) px its pixels are, to first order,
    where they were under K_from (3, 3) px up to scale: moving the principal point from c_from to c_to shifts the
    normalised coordinates by d = (c_from - c_to) / f_to, as the rotation by (-d_y, d_x, 0) rad does. (The scale
    f_from / f_to the step fits alone: moving the depth to match it too changes nothing measurable.)"""
    fx, fy, cx, cy = k_to.tolist()
    return np.array([(cy - K_from[1, 2]) / fy, (K_from[0, 2] - cx) / fx, 0.0])


def map_steps(
    points_2d, points_3d, k_net, K_cov_net, rvec, tvec, turn, noise_px, noise_floor_px: float, iterations: int
) -> tuple:
    """At most ``iterations`` Gauss-Newton steps of one frame's MAP cost over (pose, K) (``rectify.map_fit``'s
    model) from k_net (4,) px, the prior's mean, and the pose rvec, tvec (3,) {W}->{C} first turned by turn (3,)
    rad (None: not turned); K_cov_net (4, 4) px^2 the prior's covariance (its precision by OpenCV's Cholesky
    inverse); noise_px the 2D noise std s (px) the data term is weighted with (None: ``prior_step``'s estimate),
    floored at noise_floor_px. A step that does not lower the cost ends the steps. -> (k (4,) px, R (3, 3), tvec
    (3,) mm, cov (10, 10) the inverse Gauss-Newton Hessian at the last linearisation, weight 1 / s^2 px^-2,
    residuals (N, 2) px, their mean norm e px (``frame_mean_norm``) and the smallest Z_C mm at the result, steps
    taken). InputError when the prior's covariance or the Hessian is not positive definite. Every product in a
    fixed order (``rotated``, ``camera_rows``, ``monomial_gram``'s sums, ``matvec``), which the compiled core's
    ``dimenet_map_step`` follows to the bit for one step."""
    ok, precision = cv2.invert(K_cov_net, flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        raise InputError("the prior's covariance of K is not positive definite")
    R = cv2.Rodrigues(rvec)[0]
    if turn is not None:
        T = cv2.Rodrigues(turn)[0]
        R, tvec = rotated(T, R), rotated(T, tvec.reshape(3, 1)).ravel()
    k = k_net
    JJ, Jr, rss, r = frame_normal_equations(camera_xy_inverse_depth(points_3d, R, tvec), points_2d, k)
    if noise_px is None:
        step, cov, weight = prior_step(JJ, Jr, rss, r.size, precision, noise_floor_px=noise_floor_px)
    else:
        weight = 1.0 / max(float(noise_px), noise_floor_px) ** 2
        step, cov = posterior_step(JJ, Jr, precision, weight)
    cost, residuals, depth, steps = weight * rss, r, float(camera_rows(points_3d, R, tvec)[2].min()), 0
    for it in range(iterations):
        if it:  # the gradient with the prior's term, zero at the start k = k_net
            g = Jr * weight
            g[6:] += matvec(precision, k - k_net)
            step = matvec(cov, g) * -1.0
        k_new = k + step[6:]
        R_new, tvec_new = left_update(R, tvec, step[:3], step[3:6])
        rows = camera_rows(points_3d, R_new, tvec_new)
        depth_new = float(rows[2].min())
        np.divide(1.0, rows[2], out=rows[2])
        res = pinhole_residuals(rows, points_2d, k_matrix(k_new))
        d = k_new - k_net
        cost_new = weight * float(np.multiply(res, res).ravel().sum()) + float(
            np.multiply(d, matvec(precision, d)).sum()
        )
        if not cost_new <= cost:
            break
        k, R, tvec, cost, residuals, depth, steps = k_new, R_new, tvec_new, cost_new, res, depth_new, steps + 1
        if it + 1 < iterations:
            JJ, Jr, _, r = frame_normal_equations(camera_xy_inverse_depth(points_3d, R, tvec), points_2d, k)
            cov = prior_posterior(JJ, precision, weight)
    return k, R, tvec, cov, weight, np.ascontiguousarray(residuals.T), frame_mean_norm(residuals), depth, steps
