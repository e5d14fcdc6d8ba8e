"""A board's grid of corners in the image: grid units, the board model (homography + lens distortion), turns.

Grid units: inner corner (i, j) of an (nx, ny) pattern sits at (i, j), corners row by row (j outer, i
inner), as the rig numbers them. A detection's grid may be larger than its rig pattern (``grid``
(mx, my) >= (nx, ny)): the rows of corners where a board meets a neighbour at a fold (see
``refine.grow``); ``placements`` lists where the rig pattern may sit in it.

The board model maps grid units to native px: a homography to undistorted px, then the division model of
radial lens distortion about the image centre (``geometry.lens_division``). It is fitted per board, with
one term or two (``lens_division.fit_coefficients``), the homography refitted by least squares for each
trial of the coefficients, and absorbs a lens's barrel or pincushion distortion, which a homography alone
cannot (models_spec/ingest.md, "Acceptance").

Pixels: x right, y down, origin at the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime.geometry import lens_division


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
    coefficients ``k`` (k1, k2) about ``centre`` (2,) px, radii normalised by ``scale`` px."""

    H: np.ndarray
    k: tuple[float, float]
    centre: np.ndarray
    scale: float

    def undistort(self, px: np.ndarray) -> np.ndarray:
        """(n, 2) native px -> undistorted px."""
        return lens_division.undistort(px, self.k, self.centre, self.scale)

    def distort(self, px: np.ndarray) -> np.ndarray:
        """(n, 2) undistorted px -> native px (NaN where the lens has no inverse: ``lens_division.distort``)."""
        return lens_division.distort(px, self.k, self.centre, self.scale)

    def predict(self, grid: np.ndarray) -> np.ndarray:
        """(n, 2) grid units -> native px."""
        return self.distort(cv2.perspectiveTransform(grid.reshape(-1, 1, 2), self.H).reshape(-1, 2))


def _homography(grid: np.ndarray, px: np.ndarray) -> Optional[np.ndarray]:
    """Least-squares homography grid -> px (n >= 4 rows), None when degenerate."""
    H = cv2.findHomography(grid, px, 0)[0]
    return None if H is None or not np.isfinite(H).all() else H


def _fit(grid: np.ndarray, px: np.ndarray, image_size: tuple[int, int], k, terms: int, start=None) -> BoardModel:
    """The board model of corners ``px`` (n, 2) at ``grid`` (n, 2): distortion ``k`` kept when not None, else
    fitted with ``terms`` (1 or 2) terms (two from ``start`` (k1, k2) when given, else from the one-term fit);
    its ``H`` None when the corners fix no homography."""
    w, h = image_size
    centre, scale = np.array([(w - 1) / 2.0, (h - 1) / 2.0]), max(w, h) / 2.0

    def model(ks) -> tuple[BoardModel, np.ndarray]:
        """The board model of distortion ``ks`` and the corners it undistorts (n, 2) px."""
        m = BoardModel(np.eye(3), lens_division.coefficients(ks), centre, scale)
        undistorted = m.undistort(px)
        return BoardModel(_homography(grid, undistorted), m.k, centre, scale), undistorted

    def misfit(ks) -> np.ndarray:
        m, undistorted = model(ks)
        if m.H is None:
            return np.full(px.size, np.inf)
        return (cv2.perspectiveTransform(grid.reshape(-1, 1, 2), m.H).reshape(-1, 2) - undistorted).ravel()

    if k is None:
        k = lens_division.fit_coefficients(misfit, terms, start)
    return model(k)[0]


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
