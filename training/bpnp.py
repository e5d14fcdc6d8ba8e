"""Batched, exact BPnP: the weighted PnP optimum as a differentiable torch layer.

``solve_pnp(points_2d, points_3d, weights, K)`` returns the pose {W}->{C}
(X_C = R(rvec) X_W + tvec; rvec axis-angle in rad, tvec in mm) minimising

    E = sum_i w_i ||pi(K, R X_i + t) - x_i||^2   (px^2),

with pi the zero-skew pinhole projection: only fx, fy, cx, cy of K are read (the
other entries are ignored and get a zero gradient), as in ``dimenet.runtime.geometry``.

Forward: an SQPnP start per frame (OpenCV; the only per-frame Python loop), then
batched Levenberg-Marquardt in torch with analytic Jacobians (rotation as a left perturbation R <- exp(d) R) until every
frame's step is below ``STEP_TOLERANCE``.

Backward: the implicit function theorem. At the optimum the gradient g of E over the
pose vanishes, so d pose / d theta = -H^-1 dg/dtheta with H the exact Hessian, i.e.
including the second-order terms sum_i w_i r_i . d2 r_i (Gauss-Newton drops them).
Everything is analytic and batched (no autograd inside); the backward itself is not
differentiable (double backward raises). H and dg/dtheta are taken in the local coordinates
(d, t) and mapped to (rvec, tvec) through the left Jacobian of SO(3),
R(rvec + e) = exp(J_l(rvec) e) R(rvec): at a stationary point this is exactly the
derivative of the optimum of E expressed in (rvec, tvec), because the curvature of
the change of coordinates only enters multiplied by g = 0.

All tensors must be float64 CPU tensors (an InputError otherwise: float32 cannot hold a
converged optimum to the precision the implicit gradient relies on). Points with weight
0 have no effect at all, whatever their values (even NaN), and get zero gradients;
weights get no gradient. Frames whose pose is not a strict isolated
optimum (fewer than 4 weighted points, coincident or collinear points, non-finite
values, points behind the camera, a singular Hessian) raise InputError naming the frame.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import cv2
import numpy as np
import torch
from torch.autograd.function import once_differentiable

from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import MIN_DEPTH_MM, MIN_POSE_POINTS, check_not_degenerate, solve_pnp_start

MAX_ITERATIONS = 50
# A frame has converged when its rotation step is below this (rad) and its translation
# step below this times max(|t|, 1 mm) (mm).
STEP_TOLERANCE = 1e-12
# Levenberg-Marquardt damping (relative to diag(H)): start, floor, and failure ceiling.
DAMPING_START, DAMPING_MIN, DAMPING_MAX = 1e-6, 1e-12, 1e8
# A frame's step only counts as converged while the damping barely shortens it.
DAMPING_CONVERGED = 1e-3
# Steps below this (rad; mm per mm of |t|) are taken even if the cost rises: that close to
# the optimum the cost difference is rounding noise and Gauss-Newton converges on its own.
NEAR_STEP = 1e-7
# Smallest eigenvalue of the Jacobi-scaled exact Hessian (eigenvalues sum to 6) that
# still counts as invertible.
MIN_SCALED_EIGENVALUE = 1e-10


@dataclass(frozen=True)
class _Problem:
    """Masked inputs of B frames: masked points replaced by harmless values."""

    x: torch.Tensor  # (B, N, 2) px
    X: torch.Tensor  # (B, N, 3) mm, {W}
    w: torch.Tensor  # (B, N) weights, 0 on masked points
    use: torch.Tensor  # (B, N) bool, weight > 0
    kp: torch.Tensor  # (B, 4) fx, fy, cx, cy in px


@dataclass(frozen=True)
class _State:
    """Pose {W}->{C} of B frames and the projection quantities at it."""

    R: torch.Tensor  # (B, 3, 3)
    t: torch.Tensor  # (B, 3) mm
    a: torch.Tensor  # (B, N, 3) R X in mm (the rotated point, before translation)
    inv_z: torch.Tensor  # (B, N) 1/depth in 1/mm (1 on masked points)
    xn: torch.Tensor  # (B, N) normalised image x = X_C / Z_C
    yn: torch.Tensor  # (B, N) normalised image y = Y_C / Z_C
    r: torch.Tensor  # (B, N, 2) residual pi - x in px (finite garbage on masked points)
    cost: torch.Tensor  # (B,) E in px^2; inf where a weighted point is not in front
    J: torch.Tensor  # (B, N, 2, 6) d r / d (d, t), per point, unweighted


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices, skew(a) @ b == cross(a, b)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(v.shape + (3,))


def _so3_exp(v: torch.Tensor) -> torch.Tensor:
    """(B, 3) axis-angle (rad) -> (B, 3, 3) rotation matrices (Rodrigues' formula)."""
    theta2 = (v * v).sum(-1)[:, None, None]
    theta = theta2.sqrt()
    small = theta < 1e-6
    safe = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24.0, 2.0 * (torch.sin(safe / 2.0) / safe) ** 2)  # (1 - cos) / theta^2
    S = _skew(v)
    return torch.eye(3, dtype=v.dtype) + a * S + b * (S @ S)


def _so3_log(R: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) rotation matrices -> (B, 3) axis-angle (rad) with angle in [0, pi].

    Away from pi the axis comes from the skew part of R; near pi (where that part
    vanishes) from the largest column of the symmetric part, signed by the skew part.
    """
    s = 0.5 * torch.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)
    sin = s.norm(dim=-1)
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.atan2(sin, cos)
    from_skew = s * torch.where(sin > 0, theta / torch.where(sin > 0, sin, 1.0), 1.0)[:, None]
    # Near pi: (R + R^T)/2 = cos I + (1 - cos) axis axis^T.
    sym = 0.5 * (R + R.transpose(1, 2)) - cos[:, None, None] * torch.eye(3, dtype=R.dtype)
    outer = sym / (1.0 - cos).clamp_min(1.0)[:, None, None]  # only used where cos < 0
    col = outer.diagonal(dim1=-2, dim2=-1).argmax(-1)
    axis = torch.take_along_dim(outer, col[:, None, None].expand(-1, 3, 1), 2)[..., 0]
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    axis = torch.where((axis * s).sum(-1, keepdim=True) < 0, -axis, axis)
    near_pi = (cos < 0) & (sin < 1e-3)
    return torch.where(near_pi[:, None], theta[:, None] * axis, from_skew)


def _left_jacobian(v: torch.Tensor) -> torch.Tensor:
    """(B, 3) axis-angle (rad) -> (B, 3, 3) J_l with exp(v + e) = exp(J_l e) exp(v) to first order."""
    theta2 = (v * v).sum(-1)[:, None, None]
    theta = theta2.sqrt()
    small = theta < 1e-3
    safe = torch.where(small, torch.ones_like(theta), theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, 2.0 * (torch.sin(safe / 2.0) / safe) ** 2)
    c = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (safe - torch.sin(safe)) / safe**3)
    S = _skew(v)
    return torch.eye(3, dtype=v.dtype) + b * S + c * (S @ S)


def _raise_for_first(bad: torch.Tensor, message: str) -> None:
    """Raise InputError("frame b: message") for the first frame b where ``bad`` (B,) is true."""
    if bool(bad.any()):
        raise InputError(f"frame {int(torch.nonzero(bad)[0])}: {message}")


def _check_inputs(points_2d, points_3d, K, weights) -> None:
    """Raise InputError on wrong types, dtypes, shapes or weights; name the frame for non-finite values."""
    named = {"points_2d": points_2d, "points_3d": points_3d, "K": K, "weights": weights}
    for name, value in named.items():
        if not isinstance(value, torch.Tensor) or value.dtype != torch.float64 or value.device.type != "cpu":
            raise InputError(
                f"{name} must be a float64 CPU torch tensor, got {getattr(value, 'dtype', type(value))}"
                f" on {getattr(value, 'device', '-')}"
            )
    if points_2d.ndim != 3 or points_2d.shape[-1] != 2:
        raise InputError(f"points_2d must have shape (B, N, 2), got {tuple(points_2d.shape)}")
    B, N = points_2d.shape[:2]
    for name, shape in (("points_3d", (B, N, 3)), ("K", (B, 3, 3)), ("weights", (B, N))):
        if tuple(named[name].shape) != shape:
            raise InputError(f"{name} must have shape {shape}, got {tuple(named[name].shape)}")
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise InputError("weights must be finite and >= 0")
    use = weights > 0
    finite = torch.isfinite(K).all((1, 2))
    for points in (points_2d, points_3d):
        finite &= (torch.isfinite(points).all(-1) | ~use).all(-1)
    _raise_for_first(~finite, "non-finite values in K or in a weighted point")
    _raise_for_first((K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0), "the focal lengths fx, fy must be > 0 px")


def _problem(points_2d, points_3d, K, weights) -> _Problem:
    """Detached masked problem; masked points get x = 0 px and X = 0 mm (their weight is 0)."""
    use = weights > 0
    x = torch.where(use[..., None], points_2d, 0.0)
    X = torch.where(use[..., None], points_3d, 0.0)
    kp = torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]], -1)
    return _Problem(x=x, X=X, w=torch.where(use, weights, 0.0), use=use, kp=kp)


def _start(problem: _Problem) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame SQPnP start on the weighted points -> R (B, 3, 3), t (B, 3) mm."""
    x, X, use = problem.x.numpy(), problem.X.numpy(), problem.use.numpy()
    K = np.zeros((3, 3))
    r0, t0 = np.empty((len(x), 3)), np.empty((len(x), 3))
    for b in range(len(x)):
        if use[b].sum() < MIN_POSE_POINTS:
            raise InputError(f"frame {b}: {int(use[b].sum())} weighted points, a pose needs >= {MIN_POSE_POINTS}")
        fx, fy, cx, cy = problem.kp[b].tolist()
        K[...] = [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
        try:
            check_not_degenerate(x[b, use[b]], X[b, use[b]])
            r0[b], t0[b] = solve_pnp_start(x[b, use[b]], X[b, use[b]], K)
        except (InputError, cv2.error) as err:
            raise InputError(f"frame {b}: {err}") from None
    return _so3_exp(torch.from_numpy(r0)), torch.from_numpy(t0)


def _evaluate(problem: _Problem, R: torch.Tensor, t: torch.Tensor) -> _State:
    """Residuals, cost and analytic residual Jacobians of every point at the pose (R, t)."""
    fx, fy, cx, cy = (k[:, None] for k in problem.kp.unbind(-1))
    a = problem.X @ R.transpose(1, 2)
    Xc = a + t[:, None, :]
    z = torch.where(problem.use, Xc[..., 2], 1.0)
    inv_z = 1.0 / z
    xn, yn = Xc[..., 0] * inv_z, Xc[..., 1] * inv_z
    r = torch.stack([fx * xn + cx, fy * yn + cy], -1) - problem.x
    cost = (problem.w * (r * r).sum(-1)).sum(-1)
    cost = torch.where((z > MIN_DEPTH_MM).all(-1), cost, torch.inf)
    ax, ay, az = a.unbind(-1)
    one, zero = torch.ones_like(xn), torch.zeros_like(xn)
    # J = P M with P = d pi / d X_C and M = d X_C / d (d, t) = [-skew(a), I].
    Ju = (fx * inv_z)[..., None] * torch.stack([-xn * ay, az + xn * ax, -ay, one, zero, -xn], -1)
    Jv = (fy * inv_z)[..., None] * torch.stack([-az - yn * ay, yn * ax, ax, zero, one, -yn], -1)
    return _State(R=R, t=t, a=a, inv_z=inv_z, xn=xn, yn=yn, r=r, cost=cost, J=torch.stack([Ju, Jv], -2))


def _select(mask: torch.Tensor, new: _State, old: _State) -> _State:
    """Per frame, ``new`` where mask (B,) is true, else ``old``."""

    def pick(n, o):
        return torch.where(mask.reshape((-1,) + (1,) * (n.ndim - 1)), n, o)

    return _State(**{f.name: pick(getattr(new, f.name), getattr(old, f.name)) for f in fields(_State)})


def _normal_equations(problem: _Problem, state: _State) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Newton H = sum w J^T J (B, 6, 6) and gradient g = sum w J^T r (B, 6) (E / 2)."""
    B = len(state.J)
    J = state.J.reshape(B, -1, 6)
    Jw = (state.J * problem.w[..., None, None]).reshape(B, -1, 6).transpose(1, 2)
    return Jw @ J, (Jw @ state.r.reshape(B, -1, 1))[..., 0]


def _refine(problem: _Problem, state: _State) -> _State:
    """Batched Levenberg-Marquardt from ``state`` until every frame's step is below tolerance."""
    B = len(state.t)
    lam = torch.full((B,), DAMPING_START, dtype=torch.float64)
    active = torch.ones(B, dtype=torch.bool)
    for _ in range(MAX_ITERATIONS):
        H, g = _normal_equations(problem, state)
        diag = H.diagonal(dim1=-2, dim2=-1)
        Hd = H + torch.diag_embed(lam[:, None] * diag.clamp_min(1e-300))
        step, info = torch.linalg.solve_ex(Hd, -g)
        solved = (info == 0) & torch.isfinite(step).all(-1)
        step = torch.where((solved & active)[:, None], step, 0.0)
        t_scale = state.t.norm(dim=-1).clamp_min(1.0)
        size = torch.maximum(step[:, :3].abs().amax(-1), step[:, 3:].abs().amax(-1) / t_scale)
        candidate = _evaluate(problem, _so3_exp(step[:, :3]) @ state.R, state.t + step[:, 3:])
        near = (size <= NEAR_STEP) & torch.isfinite(candidate.cost)
        better = solved & active & ((candidate.cost <= state.cost) | near)
        state = _select(better, candidate, state)
        lam = torch.where(better, (lam / 10.0).clamp_min(DAMPING_MIN), lam * 10.0)
        active &= ~(solved & (size <= STEP_TOLERANCE) & (lam <= DAMPING_CONVERGED))
        if not bool(active.any()) or bool((lam[active] > DAMPING_MAX).any()):
            break
    _raise_for_first(active, "PnP did not converge (no isolated optimum in front of the camera)")
    return state


def _second_order_terms(problem: _Problem, state: _State) -> tuple[torch.Tensor, torch.Tensor]:
    """Per point q = P^T r (B, N, 3) px^2/mm, P = d pi / dX_C, and the entries (alpha, beta, gamma)
    (B, N, 3) px^2/mm^2 of S = sum_c r_c d2 pi_c / dX_C^2 = [[0, 0, -alpha], [0, 0, -beta], [-alpha, -beta, gamma]].
    """
    fx, fy = problem.kp[:, None, 0], problem.kp[:, None, 1]
    ru, rv = state.r.unbind(-1)
    pu, pv = fx * ru * state.inv_z, fy * rv * state.inv_z
    q = torch.stack([pu, pv, -(pu * state.xn + pv * state.yn)], -1)
    alpha, beta = pu * state.inv_z, pv * state.inv_z
    gamma = 2.0 * (alpha * state.xn + beta * state.yn)
    return q, torch.stack([alpha, beta, gamma], -1)


def _exact_hessian(problem: _Problem, state: _State) -> torch.Tensor:
    """(B, 6, 6) exact Hessian of E/2 over the local pose (d, t) at ``state``.

    H = sum_i w_i [J^T J + M^T S M + blockdiag(T, 0)] with M = d X_C / d(d, t) = [-skew(a), I]
    (rows Mx, My, Mz), S from ``_second_order_terms`` so that
    M^T S M = Mz V^T + V Mz^T with V = -alpha Mx - beta My + gamma/2 Mz, and
    T = (q a^T + a q^T)/2 - (q . a) I from the second-order term of exp(d) a.
    """
    H_gn, _ = _normal_equations(problem, state)
    q, S = _second_order_terms(problem, state)
    alpha, beta, half_gamma = S[..., 0], S[..., 1], 0.5 * S[..., 2]
    ax, ay, az = state.a.unbind(-1)
    w = problem.w
    one, zero = torch.ones_like(ax), torch.zeros_like(ax)
    Mz = torch.stack([ay, -ax, zero, zero, zero, one], -1)
    V = w[..., None] * torch.stack(
        [beta * az + half_gamma * ay, -alpha * az - half_gamma * ax, alpha * ay - beta * ax, -alpha, -beta, half_gamma],
        -1,
    )
    A = Mz.transpose(1, 2) @ V
    qa = (w[..., None] * q).transpose(1, 2) @ state.a
    trace = qa.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
    T = 0.5 * (qa + qa.transpose(1, 2)) - trace * torch.eye(3, dtype=torch.float64)
    H = H_gn + A + A.transpose(1, 2)
    H[:, :3, :3] += T
    return H


def _check_hessian(H: torch.Tensor) -> None:
    """Raise InputError naming the frames whose exact Hessian is not safely positive definite."""
    d = H.diagonal(dim1=-2, dim2=-1)
    ok = torch.isfinite(H).all((1, 2)) & (d > 0).all(-1)
    scale = torch.where(ok[:, None], d, 1.0).rsqrt()
    Hs = torch.where(ok[:, None, None], H, torch.eye(6, dtype=H.dtype)) * scale[:, :, None] * scale[:, None, :]
    ok &= torch.linalg.eigvalsh(Hs)[:, 0] > MIN_SCALED_EIGENVALUE
    _raise_for_first(~ok, "singular PnP optimum (the exact Hessian is not invertible)")


def _input_gradients(problem: _Problem, state: _State, u: torch.Tensor):
    """-(dg/dtheta)^T u for theta = points_2d, points_3d, K, given u = H^-1 v (B, 6), g = sum w J^T r.

    Per point, with m = M u (mm) and J u = P m (px): since dr/dx = -I, grad x = w J u;
    since g depends on a = R X through M(a), P(X_C) and r(X_C),
    grad a = -w (q x u_d + (P^T P + S) m) and grad X = R^T grad a; K enters through P and r.
    Returns gradients of shapes (B, N, 2), (B, N, 3) and (B, 3, 3), zero on masked points.
    """
    fx, fy = problem.kp[:, None, 0], problem.kp[:, None, 1]
    q, S = _second_order_terms(problem, state)
    alpha, beta, gamma = S.unbind(-1)
    m = torch.cross(u[:, None, :3].expand_as(state.a), state.a, dim=-1) + u[:, None, 3:]  # M u
    mx, my, mz = m.unbind(-1)
    ju, jv = fx * state.inv_z * (mx - state.xn * mz), fy * state.inv_z * (my - state.yn * mz)  # J u
    w = problem.w
    grad_2d = w[..., None] * torch.stack([ju, jv], -1)
    Cm = torch.stack(
        [
            fx * state.inv_z * ju - alpha * mz,
            fy * state.inv_z * jv - beta * mz,
            -(fx * state.xn * ju + fy * state.yn * jv) * state.inv_z - alpha * mx - beta * my + gamma * mz,
        ],
        -1,
    )
    grad_a = -w[..., None] * (torch.cross(q, u[:, None, :3].expand_as(q), dim=-1) + Cm)
    grad_3d = grad_a @ state.R  # a = R X
    ru, rv = state.r.unbind(-1)
    wju, wjv = w * ju, w * jv
    grad_K = torch.zeros(len(w), 3, 3, dtype=torch.float64)
    grad_K[:, 0, 0] = -(wju * (ru / fx + state.xn)).sum(-1)
    grad_K[:, 1, 1] = -(wjv * (rv / fy + state.yn)).sum(-1)
    grad_K[:, 0, 2] = -wju.sum(-1)
    grad_K[:, 1, 2] = -wjv.sum(-1)
    return grad_2d, grad_3d, grad_K


class _BPnP(torch.autograd.Function):
    """Weighted PnP optimum with implicit-function-theorem gradients (see module docstring)."""

    @staticmethod
    def forward(ctx, points_2d, points_3d, K, weights):
        problem = _problem(points_2d.detach(), points_3d.detach(), K.detach(), weights.detach())
        R0, t0 = _start(problem)
        state = _refine(problem, _evaluate(problem, R0, t0))
        H = _exact_hessian(problem, state)
        _check_hessian(H)
        rvec = _so3_log(state.R)
        ctx.problem, ctx.state, ctx.H = problem, state, H
        ctx.left_jacobian = _left_jacobian(rvec)
        return rvec, state.t.clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_rvec, grad_tvec):
        # dL/dd = J_l^-T dL/drvec, then u = H^-1 (dL/dd, dL/dt).
        grad_d = torch.linalg.solve(ctx.left_jacobian.transpose(1, 2), grad_rvec)
        u = torch.linalg.solve(ctx.H, torch.cat([grad_d, grad_tvec], -1))
        grad_2d, grad_3d, grad_K = _input_gradients(ctx.problem, ctx.state, u)
        return grad_2d, grad_3d, grad_K, None


def solve_pnp(
    points_2d: torch.Tensor, points_3d: torch.Tensor, weights: torch.Tensor, K: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted least-squares PnP optimum of B frames, differentiable w.r.t. points_2d, points_3d and K.

    points_2d (B, N, 2) px; points_3d (B, N, 3) mm in {W}; weights (B, N) >= 0, 0 masks a
    point; K (B, 3, 3) px (fx, fy, cx, cy read). All float64 (the argument order of
    ``geometry.least_squares.solve_pnp``). Returns rvec (B, 3) rad and
    tvec (B, 3) mm of the pose {W}->{C}. Raises InputError on bad input or a frame
    without an isolated optimum (the message names the frame).
    """
    _check_inputs(points_2d, points_3d, K, weights)
    return _BPnP.apply(points_2d, points_3d, K, weights)


def project(points_3d: torch.Tensor, K: torch.Tensor, rvec: torch.Tensor, tvec: torch.Tensor) -> torch.Tensor:
    """Differentiable pinhole projection (autograd): {W} points (B, N, 3) mm -> pixels (B, N, 2)
    under K (B, 3, 3) (fx, fy, cx, cy read) and the pose {W}->{C} rvec, tvec (B, 3)."""
    Xc = torch.einsum("bij,bnj->bni", _so3_exp(rvec), points_3d) + tvec[:, None, :]
    z = Xc[..., 2].clamp_min(MIN_DEPTH_MM)
    u = K[:, 0, 0, None] * Xc[..., 0] / z + K[:, 0, 2, None]
    v = K[:, 1, 1, None] * Xc[..., 1] / z + K[:, 1, 2, None]
    return torch.stack([u, v], -1)
