"""One frame's Gauss-Newton normal equations over (pose, K), in closed form: mode map's hot path.

They are the LM core's (``least_squares``) Jacobian products J^T J and J^T r for the pose
perturbed on the left of X_C, formed from nine per-point monomials instead of J itself
(tests/geometry/test_least_squares.py holds them equal to the core's; the speed against the core's
Jacobian: models_spec/BENCHMARKS.md).

The products the feature's data step and mode map's step read (``monomial_gram``, ``frame_normal_equations``,
``gram_normal_equations``, ``prior_step``) are elementwise products summed by numpy in an order it fixes (a
pairwise sum along a contiguous row, or a sum over an outer axis, first to last), not BLAS products, whose summation
order and fused multiply-adds depend on the machine's kernel: the data step's Hessian can have a
condition number near 1e9 (a single plane), so one last-bit change anywhere moves its inputs by 1e-7.
In this order the compiled core (runtime/native/dimenet_core.c, the Gram, its normal equations and the prior
step) computes the same numbers to the bit."""

from __future__ import annotations

import cv2
import numpy as np

from dimenet.runtime.errors import InputError


def _jacobian_basis() -> np.ndarray:
    """(3, 20, 9): the rows of ``frame_normal_equations``'s coefficient matrix C (20 x 9) as
    C = fx B[0] + fy B[1] + B[2]. Row 2j + c (c = 0: u, 1: v) holds dr_c/dp_j in the basis
    q = [1, a, b, ab, a^2, b^2, 1/Z, a/Z, b/Z] of the point's normalised coordinates a = X/Z,
    b = Y/Z, for p = (w (3) rad, tau (3) mm, fx, fy, cx, cy) with the pose perturbed on the left."""
    B = np.zeros((3, 10, 2, 9))
    fx, fy, one = 0, 1, 2
    # du/dp = fx [-ab, 1 + a^2, -b, 1/Z, 0, -a/Z], then [a, 0, 1, 0] for (fx, fy, cx, cy).
    B[fx, 0, 0, 3], B[fx, 1, 0, 0], B[fx, 1, 0, 4], B[fx, 2, 0, 2] = -1.0, 1.0, 1.0, -1.0
    B[fx, 3, 0, 6], B[fx, 5, 0, 7], B[one, 6, 0, 1], B[one, 8, 0, 0] = 1.0, -1.0, 1.0, 1.0
    # dv/dp = fy [-1 - b^2, ab, a, 0, 1/Z, -b/Z], then [0, b, 0, 1].
    B[fy, 0, 1, 0], B[fy, 0, 1, 5], B[fy, 1, 1, 3], B[fy, 2, 1, 1] = -1.0, -1.0, 1.0, 1.0
    B[fy, 4, 1, 6], B[fy, 5, 1, 8], B[one, 7, 1, 2], B[one, 9, 1, 0] = 1.0, -1.0, 1.0, 1.0
    return B.reshape(3, 20 * 9)


JACOBIAN_BASIS = _jacobian_basis()  # also the full graph's (export.full_graph)
# The upper triangle of the 11 x 11 Gram in row order: the pairs of monomials ``monomial_gram`` sums, in
# two blocks (a (66, N) product would be a fresh mmap and its page faults at 320 points: 5 times the time).
_GRAM_ROWS, _GRAM_COLS = np.triu_indices(11)
_GRAM_BLOCKS = (slice(0, 33), slice(33, 66))


def _monomials(xy_inv_z: np.ndarray) -> np.ndarray:
    """(11, N): rows 0-8 the monomials q = [1, a, b, ab, a^2, b^2, 1/Z, a/Z, b/Z] (a = X/Z, b = Y/Z)
    of the points xy_inv_z (3, N) (X, Y mm and 1/Z 1/mm in {C}); rows 9-10 left for the residuals."""
    Q = np.empty((11, xy_inv_z.shape[1]))
    Q[6] = inv_z = xy_inv_z[2]
    ab = np.multiply(xy_inv_z[:2], inv_z, out=Q[1:3])  # a, b
    np.multiply(ab[0], ab[1], out=Q[3])
    np.multiply(ab, ab, out=Q[4:6])
    np.multiply(ab, inv_z, out=Q[7:9])
    Q[0] = 1.0
    return Q


def monomial_gram(xy_inv_z: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """(11, 11) Q Q^T of one frame's N points, Q (11, N) their monomials q = [1, a, b, ab, a^2, b^2,
    1/Z, a/Z, b/Z] (a = X/Z, b = Y/Z) then their residuals r_u, r_v: xy_inv_z (3, N) the points
    in {C} as X, Y (mm) and 1/Z (1/mm), residuals (2, N) px. Everything the normal equations
    (``gram_normal_equations``) and the moment feature (``rectify.features``) read of the points.

    Each entry of the upper triangle is numpy's pairwise sum of its N products (the module docstring:
    a fixed order for 4 to 5 times Q Q^T's time, models_spec/BENCHMARKS.md)."""
    Q = _monomials(xy_inv_z)
    Q[9:] = residuals
    return _gram(Q)


def _gram(Q: np.ndarray) -> np.ndarray:
    """(11, 11) Q Q^T of the monomials and residuals Q (11, N), each upper entry numpy's pairwise sum."""
    upper = np.empty(len(_GRAM_ROWS))
    for block in _GRAM_BLOCKS:
        upper[block] = np.multiply(Q[_GRAM_ROWS[block]], Q[_GRAM_COLS[block]]).sum(1)
    G = np.empty((11, 11))
    G[_GRAM_ROWS, _GRAM_COLS] = upper
    G[_GRAM_COLS, _GRAM_ROWS] = upper
    return G


def gram_normal_equations(G: np.ndarray, fx: float, fy: float) -> tuple[np.ndarray, np.ndarray, float]:
    """J J^T (10, 10), J r (10,) and r.r (px^2) of ``frame_normal_equations`` from the frame's
    ``monomial_gram`` G (11, 11) and the focal lengths (px) its residuals were taken under.

    Every entry of J is a linear combination of the nine monomials q (``_jacobian_basis``), so
    J J^T = C (q q^T) C^T summed over u and v, and J r likewise. Each product's terms are summed first
    to last (a sum over an outer axis; the module docstring)."""
    C = np.dot((fx, fy, 1.0), JACOBIAN_BASIS).reshape(20, 9)  # exact: one term of each entry is not 0
    # J J^T: sum over c in (u, v) and q of (C q q^T)[2i + c, q] C[2j + c, q]; J r likewise.
    CG = _products(C[:, :, None], G[None, :9, :9], (20, 9, 9)).sum(1).reshape(10, 18)
    JJ = _products(CG.T[:, :, None], C.reshape(10, 18).T[:, None, :], (18, 10, 10)).sum(0)
    Cr = _products(C[:, :, None], G[None, :9, 9:], (20, 9, 2)).sum(1)
    return JJ, Cr[0::2, 0] + Cr[1::2, 1], float(G[9, 9] + G[10, 10])


def frame_normal_equations(
    xy_inv_z: np.ndarray, points_2d: np.ndarray, k
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """One frame's Gauss-Newton normal equations under the pinhole (fx, fy, cx, cy) px ``k``.

    xy_inv_z (3, N): the points in {C} as X, Y (mm) and 1/Z (1/mm) (``camera_xy_inverse_depth``);
    points_2d (N, 2) px. With r the residuals pi(K, X_C) - x and J (10, 2N) their Jacobian for
    p = (w (3) rad, tau (3) mm, fx, fy, cx, cy), the pose perturbed on the left (X_C ->
    exp([w]x) X_C + tau, so R -> exp([w]x) R, t -> exp([w]x) t + tau), returns J J^T (10, 10),
    J r (10,), r.r (px^2) and r (2, N) px (the u residuals, then the v residuals): one N-long
    product of the (11, N) monomials and residuals with themselves (as ``monomial_gram``'s)
    instead of forming J, in ``monomial_gram``'s order (the compiled core's map step follows it to the bit).
    """
    fx, fy, cx, cy = k
    Q = _monomials(xy_inv_z)
    r = np.multiply(Q[1:3], ((fx,), (fy,)), out=Q[9:])  # the residuals from a, b in place
    r += ((cx,), (cy,))
    r -= points_2d.T
    return (*gram_normal_equations(_gram(Q), fx, fy), r)


def prior_step(
    JJ: np.ndarray, Jr: np.ndarray, rss: float, n_residuals: int, k_precision: np.ndarray, *, noise_floor_px: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """One Gauss-Newton step over (pose, K) from ``frame_normal_equations`` (JJ (10, 10), Jr (10,),
    rss px^2 over n_residuals = 2N residuals) with a Gaussian prior on K centred where the normal
    equations were formed: k_precision (4, 4) px^-2.

    The data term is weighted by 1 / s^2, s^2 (px^2) the frame's 2D noise variance: first RSS /
    (2N - 6) (the pose alone fitted), then once more from the linearised residuals of the step
    (2N - 10 dof), floored at noise_floor_px^2. Returns (step (10,) the update of (w rad, tau mm,
    fx, fy, cx, cy px), cov (10, 10) the inverse Hessian of the weighted cost, its K block the
    posterior covariance px^2, weight 1 / s^2 px^-2)."""
    weight = _noise_weight(rss, n_residuals - 6, noise_floor_px)
    # |r - J^T step|^2 of the linearised step, from the 10x10 normal equations (the products in a fixed
    # order: the module docstring).
    step = matvec(prior_posterior(JJ, k_precision, weight), Jr) * weight
    step_JJ = _products(step[:, None], JJ, JJ.shape).sum(0)
    rss_step = rss - 2.0 * float(np.multiply(step, Jr).sum()) + float(np.multiply(step_JJ, step).sum())
    weight = _noise_weight(rss_step, n_residuals - 10, noise_floor_px)
    return (*posterior_step(JJ, Jr, k_precision, weight), weight)


def posterior_step(
    JJ: np.ndarray, Jr: np.ndarray, k_precision: np.ndarray, weight: float
) -> tuple[np.ndarray, np.ndarray]:
    """``prior_step``'s step at a known data weight 1 / s^2 (px^-2): (step (10,) = -weight cov J r, cov (10, 10)
    ``prior_posterior``'s)."""
    cov = prior_posterior(JJ, k_precision, weight)
    step = matvec(cov, Jr)
    step *= -weight
    return step, cov


def matvec(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A (n, n) times x (n,): each row's products summed by numpy's pairwise sum (not BLAS)."""
    return _products(A, x, A.shape).sum(1)


def _products(a: np.ndarray, b: np.ndarray, shape: tuple) -> np.ndarray:
    """a * b broadcast to ``shape`` into a new C-ordered array, so that a sum over its last axis is numpy's
    pairwise sum of each row and a sum over another axis adds its slices first to last (numpy lays out a
    product of strided views in its own order, where an axis's sum may be pairwise instead)."""
    return np.multiply(a, b, out=np.empty(shape))


def _noise_weight(rss: float, dof: int, floor_px: float) -> float:
    """1 / s^2 (px^-2) from a residual sum of squares rss (px^2) with dof degrees of freedom."""
    return 1.0 / max(rss / max(dof, 1), floor_px**2)


def prior_posterior(JJ: np.ndarray, k_precision: np.ndarray, weight: float) -> np.ndarray:
    """The inverse (10, 10) of the Gauss-Newton Hessian over (pose, K), weight J J^T plus the
    prior's precision k_precision (4, 4) px^-2 on K: a step is its product with the gradient.

    The Hessian is inverted with its diagonal scaled to 1 (D H D, D = diag(H)^-1/2; the inverse is
    D (D H D)^-1 D): the translation's entries go as 1/Z^2 in the scene's unit, so a scene given
    in units of 1e-6 mm or 1e11 mm would otherwise leave a Cholesky factorisation that fails.
    InputError when the Hessian is not positive definite (the points fix no pose)."""
    H = JJ * weight
    H[6:, 6:] += k_precision
    diagonal = H.diagonal()
    if not (diagonal > 0).all() or not np.isfinite(diagonal).all():
        raise InputError("the points fix no pose: the Gauss-Newton Hessian has a zero or non-finite diagonal")
    d = 1.0 / np.sqrt(diagonal)
    scale = np.outer(d, d)
    ok, inverse = cv2.invert(H * scale, flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        raise InputError("the points fix no pose: the Gauss-Newton Hessian is not positive definite")
    inverse *= scale
    return inverse
