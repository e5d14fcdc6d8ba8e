"""MAP rectification of one frame: K and pose from the frame's own points and the network's prior.

Minimises over (rvec, tvec, k = (fx, fy, cx, cy))

    sum_i ||pi(K, R X_i + t) - x_i||^2 / s^2  +  (k - k_net)^T Sigma^-1 (k - k_net)

where k_net, Sigma (4x4, px^2) are the network's Delta K mean and covariance (added to K_c)
and s^2 (px^2) the frame's 2D noise variance (``geometry.prior_step``'s, floored at
NOISE_FLOOR_PX^2).
ITERATIONS Gauss-Newton steps from k_net and the C0 pose (the PnP pose under K_c) turned to
k_net's principal point (``geometry.map_step.principal_point_turn``), with the analytic normal equations
(``geometry.frame_normal_equations``, the pose perturbed on the left); a step that does not
lower the cost ends the fit. The posterior covariance of k is the K block of the inverse
Gauss-Newton Hessian at the last linearisation, widened per parameter for the network's
correlation with the data on noisy points when the uncertainty model has one (spec >= 1.3,
``Uncertainty.posterior_scale``), and for the errors of the frame's own data (spec >= 1.10,
``Uncertainty.map_covariance``).

One frame's few Gauss-Newton steps on a well-conditioned 10x10 system: the prior keeps K
observable even from one planar view, where the data alone cannot fix it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime import native
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import solve_pnp_start
from dimenet.runtime.geometry.map_step import principal_point_turn
from dimenet.runtime.rectify.results import Fallback
from dimenet.runtime.rectify.spec import frame_within_bounds
from dimenet.runtime.rectify.uncertainty import Uncertainty

# Gauss-Newton steps: from k_net and the turned C0 pose one step lands at the optimum
# (training/METHOD.md, "MAP: steps and noise passes").
ITERATIONS = 1
NOISE_FLOOR_PX = 0.1
# The compiled posterior's parameters without an uncertainty model: no correlation, no bias (s0 unused).
NOT_WIDENED = Uncertainty(coef=np.zeros((4, 5)), correlation=np.eye(4))


@dataclass(frozen=True)
class MapFit:
    """k (4,) px (fx, fy, cx, cy); rvec (3,) rad, tvec (3,) mm {W}->{C}; K_cov (4, 4) px^2 the
    posterior covariance; residuals (N, 2) px at the result, e_px their mean norm and depth_mm the
    smallest Z_C (mm) there; steps: the Gauss-Newton steps taken (0: the first step would have
    raised the cost, the result is the start); noise_px: the frame's 2D noise std s the data term
    was weighted with."""

    k: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    K_cov: np.ndarray
    residuals: np.ndarray
    e_px: float
    depth_mm: float
    steps: int
    noise_px: float


def map_fit(
    points_2d: np.ndarray,
    points_3d: np.ndarray,
    k_net: np.ndarray,
    K_cov_net: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    *,
    iterations: int = ITERATIONS,
    K_start: np.ndarray | None = None,
    uncertainty: Uncertainty | None = None,
    noise_px: float | None = None,
) -> MapFit:
    """MAP (K, pose) of one frame: points_2d (N, 2) px, points_3d (N, 3) mm in {W}, float64;
    k_net (4,) px the network's K; K_cov_net (4, 4) px^2 its covariance; rvec, tvec a start pose
    {W}->{C}, the PnP pose under K_start (3, 3) px (e.g. the C0 pose under K_c), first turned
    to k_net's principal point by ``principal_point_turn`` (None: the pose is k_net's
    own); iterations >= 1 Gauss-Newton steps at most; uncertainty: the network's, whose
    ``map_covariance`` widens K_cov (None: the independent-errors posterior); noise_px: the frame's
    2D noise std when it is known (the evaluation's prior oracle), else (None) estimated from the
    frame's residuals by ``prior_step``. One step (``ITERATIONS``) runs in the compiled core where it
    is (``native.map_steps``), the same numbers to the bit as ``geometry.map_step``'s. InputError when
    K_cov_net or the Hessian is not positive definite."""
    k_net = np.asarray(k_net, dtype=np.float64)
    rvec, tvec = np.asarray(rvec, dtype=np.float64).ravel(), np.asarray(tvec, dtype=np.float64).ravel()
    turn = None if K_start is None else principal_point_turn(K_start, k_net)
    k, R, tvec, cov, weight, residuals, e_px, depth_mm, steps = native.map_steps(
        points_2d, points_3d, k_net, K_cov_net, rvec, tvec, turn, noise_px, NOISE_FLOOR_PX, iterations
    )
    noise_px = weight**-0.5
    K_cov = map_posterior(cov, K_cov_net, noise_px, uncertainty)
    return MapFit(
        k=k,
        rvec=cv2.Rodrigues(R)[0].ravel(),
        tvec=tvec,
        K_cov=K_cov,
        residuals=residuals,
        e_px=e_px,
        depth_mm=depth_mm,
        steps=steps,
        noise_px=noise_px,
    )


def map_posterior(cov: np.ndarray, K_cov_net: np.ndarray, noise_px: float, uncertainty: Optional[Uncertainty]):
    """The MAP posterior K_cov (4, 4) px^2: the K block of the step's inverse Hessian cov (10, 10), symmetrised,
    widened by ``uncertainty.map_covariance`` against the network's K_cov_net (4, 4) px^2 at the frame's 2D noise
    noise_px (None: not widened). In the compiled core where it is (``dimenet_map_posterior``, 1.4 against 17.5 us;
    models_spec/BENCHMARKS.md), the same numbers to the bit."""
    if native.core is not None:
        u = NOT_WIDENED if uncertainty is None else uncertainty
        K_cov = np.empty((4, 4))
        try:  # the step's arrays as they come (float64, C-contiguous)
            native.core.map_posterior(
                cov, K_cov_net, noise_px, u.data_correlation, u.noise_scale_px, u.data_bias, K_cov
            )
            return K_cov
        except TypeError:  # another layout: numpy
            pass
    K_cov = (cov[6:, 6:] + cov[6:, 6:].T) / 2
    return K_cov if uncertainty is None else uncertainty.map_covariance(K_cov, K_cov_net, noise_px)


def map_rectify(
    points_2d: np.ndarray,
    points_3d: np.ndarray,
    k_net: np.ndarray,
    K_cov_net: np.ndarray,
    k_bounds: np.ndarray,
    K_c: np.ndarray,
    pose=None,
    uncertainty: Uncertainty | None = None,
) -> tuple[MapFit | None, str | None]:
    """``map_fit`` from the C0 pose (``pose`` (rvec, tvec) under K_c (3, 3), else SQPnP here),
    checked: (fit, None), or (None, why) when there is no start pose, no step lowered the cost
    (the turned C0 pose is not k_net's optimum, so the caller's own PnP under k_net is better),
    the points fix no MAP pose (its Hessian is not positive definite: points on a line), or the
    MAP K is not finite or outside ``k_bounds`` (4, 2) px; the caller then keeps the
    DIME-Net K. ``uncertainty``: as ``map_fit``'s."""
    if pose is None:
        try:
            pose = solve_pnp_start(points_2d, points_3d, K_c)
        except InputError:
            return None, Fallback("map_no_c0_pose", "no C0 pose under K_c")
    try:
        result = map_fit(points_2d, points_3d, k_net, K_cov_net, *pose, K_start=K_c, uncertainty=uncertainty)
    except InputError:
        return None, Fallback("map_no_pose", "the points fix no MAP pose (its Hessian is not positive definite)")
    if result.steps == 0:
        return None, Fallback("map_no_step", "the MAP step did not lower the cost")
    if not frame_within_bounds(result.k.tolist(), k_bounds.tolist()):
        return None, Fallback("map_implausible", "the MAP K is implausible (outside the model's K_bounds)")
    if not result.depth_mm > 0:
        return None, Fallback("map_behind_camera", "a point lies behind the camera at the MAP pose")
    return result, None
