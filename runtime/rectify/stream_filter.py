"""One frame of the stream's Kalman filter over k = (fx, fy, cx, cy) px (``rectify.stream``'s steps 1, 3's innovation
test and 4's update), as a pure function: in the compiled core where it is (``dimenet_stream_step``,
models_spec/BENCHMARKS.md has its us), else ``stream_step_reference`` in plain floats, the same numbers to the bit.

Every sum runs left to right and S = P + R is factored by Cholesky (its lower triangle), in the order
``_cholesky`` and ``_solve`` state, which the core follows; libm's exp (``math.exp``, as the core's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dimenet.runtime import native


@dataclass(frozen=True)
class FilterStep:
    """k (4,) px and P (4, 4) px^2 after the frame; jumped: the innovation's squared Mahalanobis norm passed the
    limit and the state was reset before the update; updated: False where S = P + R is not positive definite (a
    NaN in the frame's covariance), the state then only predicted (or reset)."""

    k: np.ndarray
    P: np.ndarray
    jumped: bool
    updated: bool


def stream_step(k, P, k_prior_last, k_prior, z, R, Q, tau_s, dt_s: float, reset: bool, chi2_limit: float):
    """The state k (4,) px, P (4, 4) px^2 carried to a frame dt_s later and updated by its evidence z (4,) px with
    covariance R (4, 4) px^2: reset to (k_prior, Q) when ``reset``, else predicted by the AR(1) about the priors
    (the offset from k_prior_last, drawn back by a = exp(-dt_s / tau_s) (4,) and added to k_prior; P' = A P + (1 -
    A) Q, A = a a^T elementwise; dt_s >= 0, else ValueError); then, unless reset, a squared innovation
    (z - k)^T S^-1 (z - k) beyond chi2_limit resets the state (``jumped``); then the update with gain P S^-1, P
    symmetrised. All float64. -> FilterStep."""
    if not (reset or dt_s >= 0.0):
        raise ValueError(f"stream_step: dt_s must be >= 0 s unless the state is reset, got {dt_s!r}")
    if native.core is None:
        return stream_step_reference(k, P, k_prior_last, k_prior, z, R, Q, tau_s, dt_s, reset, chi2_limit)
    k_out, P_out = np.empty(4), np.empty((4, 4))
    arrays = (k, P, k_prior_last, k_prior, z, R, Q, tau_s)
    try:  # the stream's arrays as they come (float64, C-contiguous)
        jumped, updated = native.core.stream_step(*arrays, dt_s, reset, chi2_limit, k_out, P_out)
    except TypeError:  # another layout
        arrays = [np.ascontiguousarray(a, np.float64) for a in arrays]
        jumped, updated = native.core.stream_step(*arrays, dt_s, reset, chi2_limit, k_out, P_out)
    return FilterStep(k_out, P_out, jumped, updated)


def stream_step_reference(k, P, k_prior_last, k_prior, z, R, Q, tau_s, dt_s, reset, chi2_limit) -> FilterStep:
    """``stream_step`` in plain floats (the reference the core follows)."""
    Q = _rows(Q)
    k0 = [float(v) for v in np.ravel(k_prior)]
    if reset:
        k, P = _reset_state(k0, Q)
    else:
        k, P = _predicted(k, P, k_prior_last, k0, Q, tau_s, dt_s)
    z, R = [float(v) for v in np.ravel(z)], _rows(R)
    k, P, jumped, updated = _updated(k, P, k0, Q, z, R, reset, chi2_limit)
    return FilterStep(np.array(k), np.array(P), jumped, updated)


def _rows(M) -> list:
    return np.asarray(M, dtype=np.float64).reshape(4, 4).tolist()


def _predicted(k, P, k_prior_last, k0, Q, tau_s, dt_s) -> tuple[list, list]:
    a = [math.exp(-dt_s / t) for t in np.ravel(tau_s).tolist()]
    k = [
        p + a_i * (k_i - last)
        for p, a_i, k_i, last in zip(k0, a, np.ravel(k).tolist(), np.ravel(k_prior_last).tolist())
    ]
    P = [
        [(a[i] * a[j]) * p + (1.0 - a[i] * a[j]) * q for j, (p, q) in enumerate(zip(p_row, q_row))]
        for i, (p_row, q_row) in enumerate(zip(_rows(P), Q))
    ]
    return k, P


def _updated(k, P, k0, Q, z, R, reset, chi2_limit) -> tuple[list, list, bool, bool]:
    L, innovation = _factored(P, R, k, z)
    if L is None:
        return k, P, False, False
    jumped = False
    if not reset and _dot(innovation, _solve(L, innovation)) > chi2_limit:
        jumped = True
        k, P = _reset_state(k0, Q)
        L, innovation = _factored(P, R, k, z)
        if L is None:
            return k, P, True, False
    gain = [_solve(L, row) for row in P]  # rows of P S^-1 (S symmetric)
    k = [k_i + _dot(g, innovation) for k_i, g in zip(k, gain)]
    P = [
        [_dot([(1.0 if i == m else 0.0) - gain[i][m] for m in range(4)], [P[m][j] for m in range(4)]) for j in range(4)]
        for i in range(4)
    ]
    P = [[(P[i][j] + P[j][i]) / 2.0 for j in range(4)] for i in range(4)]
    return k, P, jumped, True


def _reset_state(k0: list, Q: list) -> tuple[list, list]:
    return list(k0), [list(row) for row in Q]


def _factored(P, R, k, z) -> tuple[list | None, list]:
    """(the Cholesky factor of S = P + R, or None; the innovation z - k)."""
    L = _cholesky([[p + r for p, r in zip(p_row, r_row)] for p_row, r_row in zip(P, R)])
    return L, [z_i - k_i for z_i, k_i in zip(z, k)]


def _dot(x, y) -> float:
    acc = x[0] * y[0]
    for a, b in zip(x[1:], y[1:]):
        acc = acc + a * b
    return acc


def _cholesky(S) -> list | None:
    """L (lower, rows) with L L^T = S from S's lower triangle, column by column; None unless every pivot is > 0."""
    L = [[0.0] * 4 for _ in range(4)]
    for j in range(4):
        d = S[j][j]
        for m in range(j):
            d = d - L[j][m] * L[j][m]
        if not d > 0.0:
            return None
        L[j][j] = math.sqrt(d)
        for i in range(j + 1, 4):
            s = S[i][j]
            for m in range(j):
                s = s - L[i][m] * L[j][m]
            L[i][j] = s / L[j][j]
    return L


def _solve(L, b) -> list:
    """x with L L^T x = b: forward, then back substitution."""
    y = [0.0] * 4
    for i in range(4):
        s = b[i]
        for m in range(i):
            s = s - L[i][m] * y[m]
        y[i] = s / L[i][i]
    x = [0.0] * 4
    for i in range(3, -1, -1):
        s = y[i]
        for m in range(i + 1, 4):
            s = s - L[m][i] * x[m]
        x[i] = s / L[i][i]
    return x
