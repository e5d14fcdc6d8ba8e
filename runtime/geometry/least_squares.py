"""Batched Levenberg-Marquardt on the reprojection error, over the pose or the pose and K.

The one LM core of the runtime: the PnP optimum under a fixed K (the metric e(K)), the joint
(K*, pose) calibration (the oracle e*) and self-calibration. Mode map's one Gauss-Newton step
uses this core's Jacobian in closed form (``normal_equations``); the training's BPnP layer
(torch, dimenet.training.bpnp) solves the same PnP problem with its exact Hessian; the lens bundle
adjustment (``lens_bundle``) chains this core's residuals and Jacobian with a lens, its frames
coupled by the lens's coefficients and so stepped together (a Schur complement). Frames are solved
together with analytic Jacobians and batched 6x6 or 10x10 normal equations; each frame
keeps its own damping. Points with weight 0 have no effect (their values are ignored).

The damping rule and the damped step (``damped``, ``next_damping``, ``lm_step``) are every fit's:
this core's, the lens bundle's (which solves its damped system by a Schur complement) and the
division lens's (``lens_division.gauss_newton``).

Parameters: rotation as a left perturbation R <- exp(d) R, translation in mm, and K as
(fx, fy, cx, cy) in px. Cost: sum_i w_i ||pi(K, R X_i + t) - x_i||^2 (px^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dimenet.runtime.errors import CalibrationError
from dimenet.runtime.geometry.pnp import dlt_camera, solve_pnp_start
from dimenet.runtime.geometry.projection import MIN_DEPTH_MM, k_matrix, k_params
from dimenet.runtime.geometry.rotation import matrix_to_rvec, rotation_matrices, rvec_to_matrix


@dataclass(frozen=True)
class FitResult:
    """Result of a batched fit over B frames."""

    K: np.ndarray  # (B, 3, 3) px
    rvec: np.ndarray  # (B, 3) rad, {W}->{C}
    tvec: np.ndarray  # (B, 3) mm, {W}->{C}
    cost: np.ndarray  # (B,) weighted sum of squared residuals, px^2
    iterations: int
    # ``calibrate(partial=True)``: per frame None, or why it gives no K (its K, pose and cost are NaN)
    reasons: tuple = ()


def residuals(points_2d, points_3d, sqrt_w, kp, R, t):
    """Weighted residuals (B, N, 2) px of pi(kp, R X + t) - x, and X_C (B, N, 3) mm, its depth z
    (clamped at MIN_DEPTH_MM) and normalised coordinates xn, yn (B, N) for ``jacobian``."""
    Xc = points_3d @ R.transpose(0, 2, 1) + t[:, None, :]
    z = np.maximum(Xc[..., 2], MIN_DEPTH_MM)
    xn, yn = Xc[..., 0] / z, Xc[..., 1] / z
    u = kp[:, None, 0] * xn + kp[:, None, 2]
    v = kp[:, None, 1] * yn + kp[:, None, 3]
    r = np.stack([u - points_2d[..., 0], v - points_2d[..., 1]], axis=-1) * sqrt_w[..., None]
    return r, Xc, z, xn, yn


def jacobian(sqrt_w, kp, Xc, t, z, xn, yn, fit_k):
    """(B, N, 2, 6 or 10) Jacobian of the weighted residuals: [rotation, translation, (K)].

    Written out element by element: d pi / d X_C = [[fx, 0, -fx xn], [0, fy, -fy yn]] / z, times
    d(exp(d) a)/dd = -skew(a) at d = 0 (a = R X) for the rotation, the identity for the translation."""
    B, N = z.shape
    fz, gz = kp[:, None, 0] / z, kp[:, None, 1] / z
    a = Xc - t[:, None, :]  # R X, the rotated point before translation
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    J = np.zeros((B, N, 2, 10 if fit_k else 6))
    J[..., 0, 0], J[..., 0, 1], J[..., 0, 2] = -fz * xn * a1, fz * (a2 + xn * a0), -fz * a1
    J[..., 1, 0], J[..., 1, 1], J[..., 1, 2] = -gz * (a2 + yn * a1), gz * yn * a0, gz * a0
    J[..., 0, 3], J[..., 0, 5] = fz, -fz * xn
    J[..., 1, 4], J[..., 1, 5] = gz, -gz * yn
    if fit_k:
        J[..., 0, 6], J[..., 0, 8] = xn, 1.0
        J[..., 1, 7], J[..., 1, 9] = yn, 1.0
    return J * sqrt_w[..., None, None]


# Levenberg-Marquardt damping, the one rule of every fit: relative to the diagonal of the
# normal equations (floored at DIAGONAL_FLOOR); it starts at DAMPING_START, is divided by
# DAMPING_FACTOR after a step that lowers the cost and multiplied by it after one that does not;
# past DAMPING_MAX no step lowers the cost (the fit is as far as it gets).
DAMPING_START = 1e-3
DAMPING_FACTOR = 10.0
DAMPING_MAX = 1e12
DIAGONAL_FLOOR = 1e-12


def damped(H: np.ndarray, damping) -> np.ndarray:
    """Normal equations H (..., n, n) damped: H + damping (...) * diag(max(diag(H), DIAGONAL_FLOOR))."""
    diag = np.maximum(np.diagonal(H, axis1=-2, axis2=-1), DIAGONAL_FLOOR)
    return H + (np.asarray(damping)[..., None] * diag)[..., None] * np.eye(H.shape[-1])


def next_damping(damping, better):
    """The damping (...) after a step: divided by DAMPING_FACTOR where ``better`` (the step lowered the
    cost), else multiplied by it."""
    return np.where(better, damping / DAMPING_FACTOR, damping * DAMPING_FACTOR)


def lm_step(H: np.ndarray, g: np.ndarray, damping) -> np.ndarray:
    """(..., n) the damped LM step -damped(H, damping)^-1 g of normal equations H (..., n, n) = J^T J,
    g (..., n) = J^T r; 0 where the damped system is singular (a step that fails, like one that
    raises the cost)."""
    return -damped_solve(damped(H, damping), g)


def damped_solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(..., n) the solutions of damped normal equations H (..., n, n) x = g (..., n); 0 for a system
    that is singular (its LM step then fails and its damping grows, as for a step that raises the cost)."""
    try:
        return np.linalg.solve(H, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        x = np.zeros_like(g)
        for b in np.ndindex(H.shape[:-2]):
            try:
                x[b] = np.linalg.solve(H[b], g[b])
            except np.linalg.LinAlgError:
                continue
        return x


def fit(
    points_2d, points_3d, weights, K, rvec, tvec, *, fit_k: bool, max_iterations: int = 50, tolerance: float = 1e-12
) -> FitResult:
    """Minimise the reprojection error of B frames from the given start.

    points_2d (B, N, 2) px; points_3d (B, N, 3) mm in {W}; weights (B, N) >= 0;
    K (B, 3, 3) start (kept fixed unless fit_k); rvec, tvec (B, 3) start pose {W}->{C}.
    Stops when every frame's relative cost decrease falls below ``tolerance``.
    """
    w = np.asarray(weights, dtype=np.float64)
    use = w > 0
    sqrt_w = np.sqrt(np.where(use, w, 0.0))
    p2 = np.where(use[..., None], points_2d, 0.0)
    p3 = np.where(use[..., None], points_3d, 0.0)
    kp = k_params(K).copy()
    R = rvec_to_matrix(rvec)
    t = np.array(tvec, dtype=np.float64)
    B = len(p2)
    n_par = 10 if fit_k else 6
    lam = np.full(B, DAMPING_START)
    r, Xc, z, xn, yn = residuals(p2, p3, sqrt_w, kp, R, t)
    cost = (r**2).sum((1, 2))
    active = np.ones(B, bool)
    it = 0
    moved = True  # the normal equations are formed again only when a frame has moved
    for it in range(1, max_iterations + 1):  # noqa: B007 (it is the count reported)
        if moved:
            J = jacobian(sqrt_w, kp, Xc, t, z, xn, yn, fit_k).reshape(B, -1, n_par)
            Jt = J.transpose(0, 2, 1)
            H = Jt @ J
            g = (Jt @ r.reshape(B, -1, 1))[..., 0]
        step = lm_step(H, g, lam)
        step[~active] = 0.0
        R_new = rotation_matrices(step[:, :3]) @ R
        t_new = t + step[:, 3:6]
        kp_new = kp + step[:, 6:10] if fit_k else kp
        r_new, Xc_new, z_new, xn_new, yn_new = residuals(p2, p3, sqrt_w, kp_new, R_new, t_new)
        cost_new = (r_new**2).sum((1, 2))
        better = (cost_new < cost) & active
        moved = bool(better.any())
        rel_gain = np.where(better, (cost - cost_new) / np.maximum(cost, 1e-300), 0.0)
        R[better], t[better], kp[better] = R_new[better], t_new[better], kp_new[better]
        r[better], Xc[better], z[better] = r_new[better], Xc_new[better], z_new[better]
        xn[better], yn[better] = xn_new[better], yn_new[better]
        cost = np.where(better, cost_new, cost)
        lam = next_damping(lam, better)
        done = (better & (rel_gain < tolerance)) | (lam > DAMPING_MAX)
        active &= ~done
        if not active.any():
            break
    return FitResult(K=k_matrix(kp), rvec=matrix_to_rvec(R), tvec=t, cost=cost, iterations=it)


def _weighted_points(points_2d, points_3d, weights, b):
    use = np.asarray(weights[b]) > 0
    return points_2d[b][use], points_3d[b][use]


def solve_pnp(points_2d, points_3d, weights, K) -> FitResult:
    """The least-squares PnP optimum of B frames under fixed K (B, 3, 3).

    Start: SQPnP per frame on the weighted points; then batched LM on the pose only.
    Raises InputError when a frame has no pose.
    """
    starts = [solve_pnp_start(*_weighted_points(points_2d, points_3d, weights, b), K[b]) for b in range(len(K))]
    rvec, tvec = (np.array(a) for a in zip(*starts))
    return fit(points_2d, points_3d, weights, K, rvec, tvec, fit_k=False)


def _dlt_starts(points_2d, points_3d, weights) -> list:
    """Per frame of B, the closed-form (K, rvec, tvec) start from its weighted points (DLT + RQ),
    or the CalibrationError saying why K is not observable from that frame."""
    starts = []
    for b in range(len(points_2d)):
        try:
            starts.append(dlt_camera(*_weighted_points(points_2d, points_3d, weights, b)))
        except CalibrationError as exc:
            starts.append(exc)
    return starts


def calibrate(points_2d, points_3d, weights, *, partial: bool = False) -> FitResult:
    """Maximum-likelihood K (fx, fy, cx, cy; zero skew) and pose of each of B frames: the one
    per-frame calibration (K*, the self-calibration baseline).

    Start: DLT + RQ per frame (closed form, needs non-coplanar points); then batched LM
    over the 10 parameters of the frames that have a start. A frame whose K is not observable
    raises CalibrationError naming it, or with ``partial`` gets NaN K, pose and cost and its
    reason in ``FitResult.reasons``.
    """
    weights = np.asarray(weights)
    starts = _dlt_starts(points_2d, points_3d, weights)
    reasons = tuple(str(s) if isinstance(s, CalibrationError) else None for s in starts)
    if not partial:
        for b, reason in enumerate(reasons):
            if reason is not None:
                raise CalibrationError(f"frame {b}: {reason}")
    B = len(starts)
    K, rvec, tvec = np.full((B, 3, 3), np.nan), np.full((B, 3), np.nan), np.full((B, 3), np.nan)
    cost = np.full(B, np.nan)
    ok = np.array([r is None for r in reasons], bool)
    iterations = 0
    if ok.any():
        K0, r0, t0 = (np.array(a) for a in zip(*(s for s, good in zip(starts, ok) if good)))
        res = fit(points_2d[ok], points_3d[ok], weights[ok], K0, r0, t0, fit_k=True)
        K[ok], rvec[ok], tvec[ok], cost[ok], iterations = res.K, res.rvec, res.tvec, res.cost, res.iterations
    return FitResult(K=K, rvec=rvec, tvec=tvec, cost=cost, iterations=iterations, reasons=reasons)
