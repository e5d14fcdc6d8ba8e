"""The division model of radial lens distortion (Fitzgibbon 2001) and its fit: the board model's lens.

A native pixel d (px, as the image holds it) undistorts to the pixel u (px) of

    u - c = (d - c) / (1 + k1·r_d² + k2·r_d⁴),   r_d = |d - c| / s,

c (px) the image centre and s (px) half the image's longer side. One term (k2 = 0) inverts in closed form, two by
Newton's method. Unlike OpenCV's model (``distortion``, stated about a camera's K), it needs no K: ingest
fits it per board with a homography (``ingest.grid``) to absorb a lens's barrel or pincushion distortion,
which a homography alone cannot (models_spec/ingest.md, "Acceptance"). ``fit_coefficients`` fits it to a
misfit: one term by Brent's method, two by Gauss-Newton damped by the LM core's rule from the one-term fit.

Pixels: x right, y down, origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import math

import numpy as np

from dimenet.runtime.geometry.least_squares import DAMPING_START, lm_step, next_damping

K_RANGE = (-0.5, 0.5)  # k1 searched (r normalised by half the longer side): beyond any phone lens
K2_RANGE = (-0.25, 0.25)  # k2 fitted within (OpenCV's k1 = -0.3, k2 = 0.1, k3 = -0.02 at f = 1.25 s needs 0.04)
K_TOLERANCE = 1e-3  # the coefficients are searched to this (k1 moves a corner < 0.01 px at 4000 px)
GAUSS_NEWTON_STEPS = 20  # at most this many steps of the two-term fit
# A two-term step that no damping below this lowers the misfit ends the fit: each try refits the misfit
# (a homography), and the step is by then under 1e-6 of the Gauss-Newton one, far below K_TOLERANCE.
GAUSS_NEWTON_MAX_DAMPING = 1e6
NEWTON_STEPS = 8  # steps inverting the two-term division model, from the one-term inverse
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def coefficients(k) -> tuple[float, float]:
    """(k1, k2) of a board model's distortion ``k``: a number (k1, one term) or a pair."""
    k = np.ravel(k).astype(np.float64)
    return float(k[0]), float(k[1]) if k.size > 1 else 0.0


def undistort(px: np.ndarray, k, centre: np.ndarray, scale: float) -> np.ndarray:
    """(n, 2) native px -> undistorted px under the division model of coefficients ``k`` (k1, k2) about ``centre``
    (2,) px, radii normalised by ``scale`` px."""
    k1, k2 = k
    d = px - centre
    r2 = np.sum((d / scale) ** 2, axis=1, keepdims=True)
    return centre + d / (1.0 + k1 * r2 + k2 * r2 * r2)


def distort(px: np.ndarray, k, centre: np.ndarray, scale: float) -> np.ndarray:
    """(n, 2) undistorted px -> native px: ``undistort``'s inverse (same arguments), exact for one term, else by
    Newton's method from the one-term inverse; NaN where it has none (or the model folds there)."""
    k1, k2 = k
    d = px - centre
    ru = np.sqrt(np.sum((d / scale) ** 2, axis=1, keepdims=True))
    disc = 1.0 - 4.0 * k1 * ru * ru
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        rd = ru * (2.0 / (1.0 + np.sqrt(np.where(disc >= 0, disc, np.nan))))  # r_d of k1 alone
        rd = np.where(np.isfinite(rd), rd, ru)
        for _ in range(NEWTON_STEPS if k2 != 0 else 0):  # r_d - r_u (1 + k1 r_d² + k2 r_d⁴) = 0
            rd = rd - (rd - ru * (1 + k1 * rd**2 + k2 * rd**4)) / (1 - ru * (2 * k1 * rd + 4 * k2 * rd**3))
        denominator = 1 + k1 * rd**2 + k2 * rd**4
        folds = denominator - rd * (2 * k1 * rd + 4 * k2 * rd**3) <= 0  # r_u no longer grows with r_d
        off = np.abs(rd - ru * denominator) > 1e-9 * (1 + ru)
        ratio = np.where(ru > 0, rd / ru, 1.0 / denominator)
    return centre + d * np.where(folds | off | ~np.isfinite(ratio), np.nan, ratio)


def fit_coefficients(misfit, terms: int, start=None) -> tuple[float, float]:
    """The coefficients (k1, k2) that minimise |misfit(k)|², ``misfit`` a function of a number (k1) or a pair
    (k1, k2) giving a residual vector: with ``terms`` 1 (k2 = 0), k1 by Brent's method within K_RANGE (or
    ``start`` when given); with 2, damped Gauss-Newton within K_RANGE x K2_RANGE from ``start`` (k1, k2),
    else from the one-term fit."""
    if start is None:
        start = (brent(lambda k1: float(np.mean(misfit(k1) ** 2)), *K_RANGE, K_TOLERANCE), 0.0)
    if terms == 1:
        return coefficients(start)
    return coefficients(gauss_newton(misfit, np.array(start, np.float64), np.array([K_RANGE, K2_RANGE])))


def _vertex(x: float, fx: float, w: float, fw: float, v: float, fv: float) -> tuple[float, float]:
    """(p, q), q >= 0: the parabola through (x, fx), (w, fw), (v, fv) has its vertex at x + p / q."""
    r, q = (x - w) * (fx - fv), (x - v) * (fx - fw)
    p, q = (x - v) * q - (x - w) * r, 2.0 * (q - r)
    return (-p, q) if q > 0 else (p, -q)


def brent(f, lo: float, hi: float, tol: float) -> float:
    """The minimiser of a unimodal scalar function ``f`` on [lo, hi], to ``tol``: Brent's method (golden-section
    steps, a step to the vertex of the parabola through the three best points where that lies inside the bracket
    and the steps shrink), ending at the last such vertex when it lies inside the final bracket."""
    a, b = lo, hi
    x = w = v = b - _GOLDEN * (b - a)
    fx = fw = fv = f(x)
    step = previous = 0.0  # the last step and the one before it
    least = tol / 4.0  # no two points nearer than this; x ends within 2 least = tol / 2 of both bracket ends
    while max(x - a, b - x) > 2.0 * least:
        middle = (a + b) / 2.0
        golden = True
        if abs(previous) > least and math.isfinite(fx + fw + fv):
            p, q = _vertex(x, fx, w, fw, v, fv)
            if abs(p) < abs(0.5 * q * previous) and q * (a - x) < p < q * (b - x):
                previous, step, golden = step, p / q, False
                if min(x + step - a, b - x - step) < 2.0 * least:
                    step = math.copysign(least, middle - x)
        if golden:
            previous = (a - x) if x >= middle else (b - x)
            step = (1.0 - _GOLDEN) * previous
        u = x + (step if abs(step) >= least else math.copysign(least, step))
        fu = f(u)
        if fu <= fx:
            a, b = (x, b) if u >= x else (a, x)
            v, fv, w, fw, x, fx = w, fw, x, fx, u, fu
        else:
            a, b = (u, b) if u < x else (a, u)
            if fu <= fw or w == x:
                v, fv, w, fw = w, fw, u, fu
            elif fu <= fv or v == x or v == w:
                v, fv = u, fu
    p, q = _vertex(x, fx, w, fw, v, fv) if math.isfinite(fx + fw + fv) else (0.0, 0.0)
    return x + p / q if q * (a - x) < p < q * (b - x) else x


def gauss_newton(f, start: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """A minimiser of |f(x)|² from ``start`` within ``bounds`` (m, 2) (Levenberg-Marquardt: the LM core's damped step,
    ``least_squares.lm_step``, on a forward-difference Jacobian), to K_TOLERANCE or GAUSS_NEWTON_STEPS steps."""
    x, r, damping = start.astype(np.float64), f(start), DAMPING_START
    for _ in range(GAUSS_NEWTON_STEPS):
        if not np.isfinite(r).all():
            break
        J = np.stack([(f(x + step) - r) / step[i] for i, step in enumerate(np.eye(len(x)) * 1e-6)], 1)
        A, g = J.T @ J, J.T @ r
        while damping < GAUSS_NEWTON_MAX_DAMPING:
            trial = np.clip(x + lm_step(A, g, damping), *bounds.T)
            r_trial = f(trial)
            if r_trial @ r_trial < r @ r:
                break
            damping = next_damping(damping, False)
        else:
            break
        moved = np.abs(trial - x).max()
        x, r, damping = trial, r_trial, next_damping(damping, True)
        if moved < K_TOLERANCE:
            break
    return x
