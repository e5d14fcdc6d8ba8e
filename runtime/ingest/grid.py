"""A board's grid of corners in the image: grid units, the board model (homography + lens distortion), turns.

Grid units: inner corner (i, j) of an (nx, ny) pattern sits at (i, j), corners row by row (j outer, i
inner), as the rig numbers them. A detection's grid may be larger than its rig pattern (``grid``
(mx, my) >= (nx, ny)): the rows of corners where a board meets a neighbour at a fold (see
``refine.grow``); ``placements`` lists where the rig pattern may sit in it.

The board model maps grid units to native px: a homography to undistorted px, then a division model of
radial lens distortion about the image centre (Fitzgibbon 2001), u - c = (d - c) / (1 + k1·r_d² + k2·r_d⁴)
with r_d = |d - c| / s, s = half the image's longer side. It is fitted per board, with one term (k2 = 0,
k1 by Brent's method, the homography by least squares for each k1) or two (k1 and k2 by damped
Gauss-Newton from the one-term fit, the homography refitted for each), and absorbs a lens's barrel or
pincushion distortion, which a homography alone cannot (models_spec/ingest.md, "Acceptance").

Pixels: x right, y down, origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

K_RANGE = (-0.5, 0.5)  # k1 searched (r normalised by half the longer side): beyond any phone lens
K2_RANGE = (-0.25, 0.25)  # k2 fitted within (OpenCV's k1 = -0.3, k2 = 0.1, k3 = -0.02 at f = 1.25 s needs 0.04)
K_TOLERANCE = 1e-3  # the coefficients are searched to this (k1 moves a corner < 0.01 px at 4000 px)
GAUSS_NEWTON_STEPS = 20  # at most this many steps of the two-term fit
NEWTON_STEPS = 8  # steps inverting the two-term division model, from the one-term inverse
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def grid_points(pattern: tuple[int, int]) -> np.ndarray:
    """(nx·ny, 2) the inner corners in grid units (i, j), row by row (j outer, i inner)."""
    nx, ny = pattern
    j, i = np.mgrid[0:ny, 0:nx]
    return np.stack([i.ravel(), j.ravel()], 1).astype(np.float64)


def corner_spacing(corners_px: np.ndarray, pattern: tuple[int, int]) -> float:
    """Smallest distance (px) between neighbouring corners found, along rows, columns and diagonals
    (inf when no two neighbours are found)."""
    nx, ny = pattern
    g = corners_px.reshape(ny, nx, 2)
    steps = [g[:, 1:] - g[:, :-1], g[1:] - g[:-1], g[1:, 1:] - g[:-1, :-1], g[1:, :-1] - g[:-1, 1:]]
    d = np.concatenate([np.linalg.norm(s, axis=-1).ravel() for s in steps])
    d = d[np.isfinite(d)]
    return float(d.min()) if d.size else float("inf")


def coefficients(k) -> tuple[float, float]:
    """(k1, k2) of a board model's distortion ``k``: a number (k1, one term) or a pair."""
    k = np.ravel(k).astype(np.float64)
    return float(k[0]), float(k[1]) if k.size > 1 else 0.0


@dataclass(frozen=True)
class BoardModel:
    """Grid units -> native px: homography ``H`` (3, 3) to undistorted px, then the division model of
    coefficients ``k`` (k1, k2) about ``centre`` (2,) px, radii normalised by ``scale`` px."""

    H: np.ndarray
    k: tuple[float, float]
    centre: np.ndarray
    scale: float

    def undistort(self, px: np.ndarray) -> np.ndarray:
        """(n, 2) native px -> undistorted px."""
        k1, k2 = self.k
        d = px - self.centre
        r2 = np.sum((d / self.scale) ** 2, axis=1, keepdims=True)
        return self.centre + d / (1.0 + k1 * r2 + k2 * r2 * r2)

    def distort(self, px: np.ndarray) -> np.ndarray:
        """(n, 2) undistorted px -> native px: the division model's inverse, exact for one term, else by Newton's
        method from the one-term inverse; NaN where it has none (or the model folds there)."""
        k1, k2 = self.k
        d = px - self.centre
        ru = np.sqrt(np.sum((d / self.scale) ** 2, axis=1, keepdims=True))
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
        return self.centre + d * np.where(folds | off | ~np.isfinite(ratio), np.nan, ratio)

    def predict(self, grid: np.ndarray) -> np.ndarray:
        """(n, 2) grid units -> native px."""
        return self.distort(cv2.perspectiveTransform(grid.reshape(-1, 1, 2), self.H).reshape(-1, 2))


def _homography(grid: np.ndarray, px: np.ndarray) -> Optional[np.ndarray]:
    """Least-squares homography grid -> px (n >= 4 rows), None when degenerate."""
    H = cv2.findHomography(grid, px, 0)[0]
    return None if H is None or not np.isfinite(H).all() else H


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


def _fit(grid: np.ndarray, px: np.ndarray, image_size: tuple[int, int], k, terms: int, start=None) -> BoardModel:
    """The board model of corners ``px`` (n, 2) at ``grid`` (n, 2): distortion ``k`` kept when not None, else
    fitted with ``terms`` (1 or 2) terms (two from ``start`` (k1, k2) when given, else from the one-term fit);
    its ``H`` None when the corners fix no homography."""
    w, h = image_size
    centre, scale = np.array([(w - 1) / 2.0, (h - 1) / 2.0]), max(w, h) / 2.0

    def model(ks) -> tuple[BoardModel, np.ndarray]:
        """The board model of distortion ``ks`` and the corners it undistorts (n, 2) px."""
        m = BoardModel(np.eye(3), coefficients(ks), centre, scale)
        undistorted = m.undistort(px)
        return BoardModel(_homography(grid, undistorted), m.k, centre, scale), undistorted

    def misfit(ks) -> np.ndarray:
        m, undistorted = model(ks)
        if m.H is None:
            return np.full(px.size, np.inf)
        return (cv2.perspectiveTransform(grid.reshape(-1, 1, 2), m.H).reshape(-1, 2) - undistorted).ravel()

    if k is None:
        if start is None:
            start = (brent(lambda k1: float(np.mean(misfit(k1) ** 2)), *K_RANGE, K_TOLERANCE), 0.0)
        k = start if terms == 1 else gauss_newton(misfit, np.array(start, np.float64), np.array([K_RANGE, K2_RANGE]))
    return model(k)[0]


def gauss_newton(f, start: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """A minimiser of |f(x)|² from ``start`` within ``bounds`` (m, 2) (damped Gauss-Newton, forward-difference
    Jacobian), to K_TOLERANCE or GAUSS_NEWTON_STEPS steps."""
    x, r, damping = start.astype(np.float64), f(start), 1e-3
    for _ in range(GAUSS_NEWTON_STEPS):
        if not np.isfinite(r).all():
            break
        J = np.stack([(f(x + step) - r) / step[i] for i, step in enumerate(np.eye(len(x)) * 1e-6)], 1)
        A, g = J.T @ J, J.T @ r
        while damping < 1e6:
            trial = np.clip(x - np.linalg.solve(A + damping * np.diag(np.diag(A) + 1e-12), g), *bounds.T)
            r_trial = f(trial)
            if r_trial @ r_trial < r @ r:
                break
            damping *= 10.0
        else:
            break
        moved = np.abs(trial - x).max()
        x, r, damping = trial, r_trial, damping / 10.0
        if moved < K_TOLERANCE:
            break
    return x


def fit_model(
    corners_px: np.ndarray, pattern: tuple[int, int], image_size: tuple[int, int], k=None, terms: int = 1
) -> Optional[BoardModel]:
    """The board model fitted to the (nx·ny, 2) px corners (NaN rows ignored) of a (width, height) px image,
    its distortion ``k`` (k1, or (k1, k2)) fitted with ``terms`` (1 or 2) terms when None, else kept (only the
    homography fitted); None when the corners found fix no homography (fewer than 4, or collinear)."""
    found = np.isfinite(corners_px).all(1)
    if found.sum() < 4:
        return None
    best = _fit(grid_points(pattern)[found], corners_px[found].astype(np.float64), image_size, k, terms)
    return None if best.H is None else best


def held_out_residuals(
    corners_px: np.ndarray, pattern: tuple[int, int], image_size: tuple[int, int], model: BoardModel
) -> np.ndarray:
    """(nx·ny,) px how far each corner lies from where the two-term board model of the other corners puts it
    (fitted from ``model``'s distortion; inf where missing or no model): a corner the model bends to fit shows."""
    grid, found = grid_points(pattern), np.isfinite(corners_px).all(1)
    out = np.full(len(corners_px), np.inf)
    for i in np.flatnonzero(found):
        others = found & (np.arange(len(found)) != i)
        if others.sum() >= 4:
            m = _fit(grid[others], corners_px[others].astype(np.float64), image_size, None, 2, model.k)
            if m.H is not None:
                out[i] = np.linalg.norm(m.predict(grid[i : i + 1])[0] - corners_px[i])
    return np.where(np.isfinite(out), out, np.inf)


def residuals(corners_px: np.ndarray, model: Optional[BoardModel], pattern: tuple[int, int]) -> np.ndarray:
    """(nx·ny,) px how far each corner lies from where the board model puts it (inf where missing or no model)."""
    if model is None:
        return np.full(len(corners_px), np.inf)
    r = np.linalg.norm(model.predict(grid_points(pattern)) - corners_px, axis=1)
    return np.where(np.isfinite(r), r, np.inf)


def canonical(corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """The corners reordered (rows reversed if needed) so that the grid is right-handed in the image.

    A board seen from its printed side shows its x (along a row) and y (down the columns) like
    the image's x and y: cross(x, y) > 0 in the y-down image.
    """
    nx, ny = pattern
    g = corners_px.reshape(ny, nx, 2)
    ex, ey = np.nanmean(g[:, -1] - g[:, 0], 0), np.nanmean(g[-1] - g[0], 0)
    return corners_px if ex[0] * ey[1] - ex[1] * ey[0] > 0 else g[::-1].reshape(-1, 2)


def placements(grid: tuple[int, int], pattern: tuple[int, int]) -> list[np.ndarray]:
    """Index arrays (nx·ny,) into a right-handed (mx, my) detection grid: a rig pattern (nx, ny) under every
    quarter turn at every offset where it fits in the grid, in the rig's corner order (empty when it fits
    nowhere). For a grid of the pattern itself: 0° and 180°, plus 90° and 270° when it is square."""
    mx, my = grid
    nx, ny = pattern
    idx = np.arange(mx * my).reshape(my, mx)
    out = []
    for k in range(4):
        turned = np.rot90(idx, k)
        rows, cols = turned.shape
        for v in range(rows - ny + 1):
            for u in range(cols - nx + 1):
                out.append(turned[v : v + ny, u : u + nx].ravel())
    return out
