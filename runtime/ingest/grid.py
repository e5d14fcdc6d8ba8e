"""A board's grid of corners in the image: grid units, the board model (homography + lens distortion), turns.

Grid units: inner corner (i, j) of an (nx, ny) pattern sits at (i, j), corners row by row (j outer, i
inner), as the rig numbers them. A detection's grid may be larger than its rig pattern (``grid``
(mx, my) >= (nx, ny)): the rows of corners where a board meets a neighbour at a fold (see
``refine.grow``); ``placements`` lists where the rig pattern may sit in it.

The board model maps grid units to native px: a homography to undistorted px, then a one-parameter
division model of radial lens distortion about the image centre (Fitzgibbon 2001),
u - c = (d - c) / (1 + k·r_d²) with r_d = |d - c| / s, s = half the image's longer side. It is fitted
per board (k by golden-section search, the homography by least squares for each k) and absorbs a lens's
barrel or pincushion distortion, which a homography alone cannot (models_spec/ingest.md, "Acceptance").

Pixels: x right, y down, origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

K_RANGE = (-0.5, 0.5)  # division coefficient searched (r normalised by half the longer side): beyond any phone lens
K_TOLERANCE = 1e-3  # golden-section search stops when k is known to this (moves a corner < 0.01 px at 4000 px)
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


@dataclass(frozen=True)
class BoardModel:
    """Grid units -> native px: homography ``H`` (3, 3) to undistorted px, then the division model of
    coefficient ``k`` about ``centre`` (2,) px, radii normalised by ``scale`` px."""

    H: np.ndarray
    k: float
    centre: np.ndarray
    scale: float

    def undistort(self, px: np.ndarray) -> np.ndarray:
        """(n, 2) native px -> undistorted px."""
        d = px - self.centre
        r2 = np.sum((d / self.scale) ** 2, axis=1, keepdims=True)
        return self.centre + d / (1.0 + self.k * r2)

    def distort(self, px: np.ndarray) -> np.ndarray:
        """(n, 2) undistorted px -> native px (the division model's exact inverse; NaN where it has none)."""
        d = px - self.centre
        r2 = np.sum((d / self.scale) ** 2, axis=1, keepdims=True)
        disc = 1.0 - 4.0 * self.k * r2
        with np.errstate(invalid="ignore"):
            return self.centre + d * (2.0 / (1.0 + np.sqrt(np.where(disc >= 0, disc, np.nan))))

    def predict(self, grid: np.ndarray) -> np.ndarray:
        """(n, 2) grid units -> native px."""
        return self.distort(cv2.perspectiveTransform(grid.reshape(-1, 1, 2), self.H).reshape(-1, 2))


def _homography(grid: np.ndarray, px: np.ndarray) -> Optional[np.ndarray]:
    """Least-squares homography grid -> px (n >= 4 rows), None when degenerate."""
    H = cv2.findHomography(grid, px, 0)[0]
    return None if H is None or not np.isfinite(H).all() else H


def _rms(grid: np.ndarray, px: np.ndarray, H: Optional[np.ndarray]) -> float:
    if H is None:
        return float("inf")
    fitted = cv2.perspectiveTransform(grid.reshape(-1, 1, 2), H).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum((fitted - px) ** 2, 1))))


def golden_section(f, lo: float, hi: float, tol: float) -> float:
    """The minimiser of a unimodal scalar function ``f`` on [lo, hi], to ``tol``."""
    a, b = lo, hi
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
    fc, fd = f(c), f(d)
    while b - a > tol:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - _GOLDEN * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + _GOLDEN * (b - a)
            fd = f(d)
    return (a + b) / 2.0


def fit_model(
    corners_px: np.ndarray, pattern: tuple[int, int], image_size: tuple[int, int], k: Optional[float] = None
) -> Optional[BoardModel]:
    """The board model fitted to the (nx·ny, 2) px corners (NaN rows ignored) of a (width, height) px image,
    its distortion coefficient ``k`` searched when None, else kept (only the homography fitted); None when the
    corners found fix no homography (fewer than 4, or collinear)."""
    grid = grid_points(pattern)
    found = np.isfinite(corners_px).all(1)
    if found.sum() < 4:
        return None
    grid, px = grid[found], corners_px[found].astype(np.float64)
    w, h = image_size
    centre, scale = np.array([(w - 1) / 2.0, (h - 1) / 2.0]), max(w, h) / 2.0

    def model(coefficient: float) -> BoardModel:
        m = BoardModel(np.eye(3), coefficient, centre, scale)
        return BoardModel(_homography(grid, m.undistort(px)), coefficient, centre, scale)

    def rms(coefficient: float) -> float:
        m = model(coefficient)
        return _rms(grid, m.undistort(px), m.H)

    best = model(golden_section(rms, *K_RANGE, K_TOLERANCE) if k is None else k)
    return None if best.H is None else best


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
