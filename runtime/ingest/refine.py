"""A detected plain board at native resolution: sub-pixel corners, the acceptance test, and its grid grown at folds.

1. ``refine``: every corner by ``cv2.cornerSubPix`` on the native grey image, with a half-window of
   SUBPIX_WINDOW_FRACTION of the corner spacing, smaller where the image edge is nearer.
2. ``refine_plain``: a corner farther than RESEED_TOLERANCE of the spacing from the board model
   (``grid.fit_model``: homography + one radial term) is started again where the model of the
   other corners puts it. The board is kept when every corner then lies within ACCEPT_TOLERANCE of
   the spacing of the model, else dropped with the reason (the largest residual and the tolerance, or
   a corner at the image edge). Where the one-term model leaves a corner beyond it (a strong lens),
   the two-term model judges instead, each corner both fitted and held out (``judged``). Real boards
   leave up to 7.7 % (paper that is not flat, print), a corner moved by 0.3 of a square 13.7 % or
   more, by 0.2 mostly more than 12 %, a grid bent over two boards 47-102 % (models_spec/ingest.md,
   "Acceptance").
3. ``grow``: where the checker pattern runs on past a side of the grid (a board meeting another one at
   a fold, with no gap between the patterns), that side gets more rows of corners, so that the
   rig's pattern can be placed in the grid by the board identification (``grid.placements``): a
   detector asked for an (nx, ny) board may return any (nx, ny) window of the larger grid.

Pixels: x right, y down, origin at the centre of the top-left pixel; corners row by row (j outer, i inner).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime.ingest.grid import (
    BoardModel,
    corner_spacing,
    fit_model,
    grid_points,
    held_out_residuals,
    residuals,
)

SUBPIX_WINDOW_FRACTION = 0.3  # cornerSubPix half-window as a fraction of the smallest corner spacing
SUBPIX_WINDOW_PX = (2, 12)  # clip of that half-window, native px
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.001)
RESEED_TOLERANCE = 0.05  # a corner farther than this fraction of the spacing from the model is refined again
ACCEPT_TOLERANCE = 0.12  # a board is kept when every corner lies within this fraction of the spacing of the model
HELD_OUT_TOLERANCE = 0.15  # and, judged by two terms, within this of where the model of the other corners puts it
TOLERANCE_MIN_PX = 1.0  # (each tolerance at least this many px)
GROW_CONTRAST = 0.5  # a grown corner's checker contrast is at least this fraction of the board's median
QUADRANT_OFFSET = 0.25  # the four squares around a corner are sampled this far from it along both axes (grid units)
QUADRANT_BOX = 0.15  # side of the square averaged there (grid units)


def tolerance_px(fraction: float, corners_px: np.ndarray, pattern: tuple[int, int]) -> float:
    """``fraction`` of the board's smallest corner spacing, at least TOLERANCE_MIN_PX (px)."""
    return max(TOLERANCE_MIN_PX, fraction * corner_spacing(corners_px, pattern))


def edge_room(corners_px: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """(n,) px the distance from each corner to the nearest image edge pixel (NaN for a NaN corner)."""
    h, w = shape[:2]
    x, y = corners_px[:, 0], corners_px[:, 1]
    return np.minimum(np.minimum(x, w - 1 - x), np.minimum(y, h - 1 - y))


def half_window(spacing_px: float, window_fraction: float = SUBPIX_WINDOW_FRACTION) -> int:
    """cornerSubPix half-window (px) for a corner spacing (px)."""
    lo, hi = SUBPIX_WINDOW_PX
    return int(np.clip(window_fraction * spacing_px, lo, hi)) if np.isfinite(spacing_px) else lo


def subpix(gray: np.ndarray, corners_px: np.ndarray, half: int) -> np.ndarray:
    """Sub-pixel corners (n, 2) px from the given starts, each with a half-window of ``half`` px or less where
    the image edge is nearer (the window stays inside, + 1 px); NaN where a start is missing or lies closer
    to the edge than the smallest window (SUBPIX_WINDOW_PX[0] + 1 px), before or after refinement."""
    lo = SUBPIX_WINDOW_PX[0]
    with np.errstate(invalid="ignore"):
        room = np.floor(edge_room(corners_px, gray.shape)) - 1
    halves = np.where(np.isfinite(room), np.minimum(half, room), -1).astype(int)
    out = np.full(corners_px.shape, np.nan)
    for h in np.unique(halves[halves >= lo]):
        use = halves == h
        pts = corners_px[use].astype(np.float32).reshape(-1, 1, 2)
        out[use] = cv2.cornerSubPix(gray, pts, (int(h), int(h)), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        out[~(edge_room(out, gray.shape) >= lo + 1)] = np.nan
    return out


def refine(
    gray: np.ndarray, corners_px: np.ndarray, pattern: tuple[int, int], window_fraction: float = SUBPIX_WINDOW_FRACTION
) -> np.ndarray:
    """Sub-pixel corners (nx·ny, 2) px on the native grey image (``cv2.cornerSubPix``), the half-window
    ``window_fraction`` of the smallest corner spacing (clipped to SUBPIX_WINDOW_PX); NaN where a corner
    is missing or too near the image edge (``subpix``)."""
    return subpix(gray, corners_px, half_window(corner_spacing(corners_px, pattern), window_fraction))


def predicted(corners_px: np.ndarray, pattern: tuple[int, int], image_size: tuple[int, int]) -> np.ndarray:
    """(nx·ny, 2) px every corner where the board model of the found (finite) corners puts it; NaN without a model."""
    model = fit_model(corners_px, pattern, image_size)
    grid = grid_points(pattern)
    return np.full_like(grid, np.nan) if model is None else model.predict(grid)


@dataclass(frozen=True)
class Refined:
    """A plain board after refinement: its corners (nx·ny, 2) px when kept, else None and ``reason``.
    ``residual_px``: its largest corner residual under the board model; ``tolerance_px``: what it may be;
    ``k``: the model's distortion coefficients (k1, k2) (``grid.BoardModel``)."""

    corners_px: Optional[np.ndarray]
    residual_px: float
    tolerance_px: float
    reason: Optional[str] = None
    k: tuple[float, float] = (0.0, 0.0)


def judged(
    corners_px: np.ndarray, pattern: tuple[int, int], image_size: tuple[int, int], model: Optional[BoardModel] = None
) -> tuple:
    """(board model, largest corner residual px, tolerance px) a board's whole corners are judged by: the
    one-term model (``model`` when already fitted to them by ``grid.fit_model``), within ACCEPT_TOLERANCE of the
    spacing; where it leaves a corner beyond that (a strong lens), the two-term model, within ACCEPT_TOLERANCE and
    every corner within HELD_OUT_TOLERANCE of where the model of the other corners puts it
    (``grid.held_out_residuals``: the second term can bend to one misplaced corner, the model of the others does
    not: a corner of a real board moved by 0.2 of the spacing is held out at 15.8 % or more, a strong lens's corners
    mostly within 10 %; models_spec/ingest.md, "Acceptance")."""
    tolerance = tolerance_px(ACCEPT_TOLERANCE, corners_px, pattern)
    model = fit_model(corners_px, pattern, image_size) if model is None else model
    worst = float(residuals(corners_px, model, pattern).max())
    if worst <= tolerance or model is None:
        return model, worst, tolerance
    two = fit_model(corners_px, pattern, image_size, terms=2)
    worst_two = float(residuals(corners_px, two, pattern).max())
    held_out = tolerance_px(HELD_OUT_TOLERANCE, corners_px, pattern)
    if worst_two <= tolerance and held_out_residuals(corners_px, pattern, image_size, two).max() <= held_out:
        return two, worst_two, tolerance
    return model, worst, tolerance


def refine_plain(gray: np.ndarray, corners_px: np.ndarray, pattern: tuple[int, int]) -> Refined:
    """A plain board's refined corners, kept when whole and on its model (see the module doc), else the reason.
    A corner started again that cannot be refined there (its start off the image) keeps its first place."""
    size = (gray.shape[1], gray.shape[0])
    refined = refine(gray, corners_px, pattern)
    if not np.isfinite(refined).all():
        return Refined(
            None, float("inf"), float("nan"), f"a corner lies within {SUBPIX_WINDOW_PX[0] + 1} px of the image edge"
        )
    model = fit_model(refined, pattern, size)
    off = residuals(refined, model, pattern) > tolerance_px(RESEED_TOLERANCE, refined, pattern)
    if off.any():
        start = np.where(off[:, None], predicted(np.where(off[:, None], np.nan, refined), pattern, size), refined)
        again = refine(gray, start, pattern)
        refined = np.where(np.isfinite(again), again, refined)  # where starting again fails, judge the first
        model = fit_model(refined, pattern, size)
    model, worst, tolerance = judged(refined, pattern, size, model)
    if not worst <= tolerance:
        return Refined(None, worst, tolerance, f"corner residual {worst:.1f} px > {tolerance:.1f} px tolerance")
    return Refined(refined, worst, tolerance, k=model.k)


def sample(gray: np.ndarray, points_px: np.ndarray) -> np.ndarray:
    """(n,) the grey level at each point (n, 2) px, bilinear; NaN outside the image (or at a NaN point)."""
    h, w = gray.shape
    x, y = points_px[:, 0], points_px[:, 1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    out = np.full(len(points_px), np.nan)
    xi, yi = np.minimum(x[inside], w - 1.001), np.minimum(y[inside], h - 1.001)
    x0, y0 = xi.astype(int), yi.astype(int)
    fx, fy = xi - x0, yi - y0

    def at(dy: int, dx: int) -> np.ndarray:
        return gray[y0 + dy, x0 + dx].astype(np.float64)

    top = at(0, 0) * (1 - fx) + at(0, 1) * fx
    bottom = at(1, 0) * (1 - fx) + at(1, 1) * fx
    out[inside] = top * (1 - fy) + bottom * fy
    return out


def quadrant_means(gray: np.ndarray, model: BoardModel, grid: np.ndarray) -> np.ndarray:
    """(n, 4) mean grey level of the four squares around each grid point (n, 2), sampled QUADRANT_OFFSET grid
    units from it towards (+, +), (−, −), (+, −), (−, +), over a QUADRANT_BOX square of 3 x 3 points there
    (NaN when one leaves the image). Close to the corner, so that past a fold (where the model, of this
    board's plane, no longer holds) the samples still fall in the squares that meet at the corner."""
    offsets = QUADRANT_OFFSET * np.array([[1.0, 1.0], [-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0]])
    spread = QUADRANT_BOX * np.stack(np.meshgrid([-0.5, 0.0, 0.5], [-0.5, 0.0, 0.5]), -1).reshape(-1, 2)
    points = grid[:, None, None, :] + offsets[None, :, None, :] + spread[None, None, :, :]
    values = sample(gray, model.predict(points.reshape(-1, 2))).reshape(len(grid), 4, len(spread))
    return values.mean(axis=2)


def _parity(grid: np.ndarray) -> np.ndarray:
    """(n,) +1 where i + j is even, -1 where odd, for grid points (n, 2)."""
    return np.where(np.round(grid).sum(1) % 2 == 0, 1.0, -1.0)


def checker_phase(means: np.ndarray, grid: np.ndarray) -> float:
    """+1 when the (+, +) and (−, −) squares of an even corner (i + j even) are the light ones, else -1:
    the board's colouring, from the quadrant means (n, 4) of its own corners (n, 2)."""
    signed = (means[:, :2].mean(1) - means[:, 2:].mean(1)) * _parity(grid)
    return 1.0 if np.nanmedian(signed) >= 0 else -1.0


def checker_contrast(means: np.ndarray, grid: np.ndarray, phase: float) -> np.ndarray:
    """(n,) how clearly each grid point (n, 2) is a corner of the board's colouring ``phase``: the darker of the
    two squares that should be light minus the lighter of the two that should be dark (grey levels; negative
    when they do not separate, NaN outside the image). The (+, +) and (−, −) squares share a colour, which
    alternates with the parity of i + j."""
    first = (_parity(grid) * phase > 0)[:, None]
    same, other = means[:, :2], means[:, 2:]
    light, dark = np.where(first, same, other), np.where(first, other, same)
    return light.min(1) - dark.max(1)


def _side_rows(grid_shape: tuple[int, int]) -> list[np.ndarray]:
    """The grid points (n, 2) one row beyond each side of an (mx, my) grid: left, right, top, bottom."""
    mx, my = grid_shape
    i, j = np.arange(mx, dtype=np.float64), np.arange(my, dtype=np.float64)
    return [
        np.stack([np.full(my, -1.0), j], 1),
        np.stack([np.full(my, float(mx)), j], 1),
        np.stack([i, np.full(mx, -1.0)], 1),
        np.stack([i, np.full(mx, float(my))], 1),
    ]


def _add_row(corners_px: np.ndarray, grid_shape: tuple[int, int], side: int, row_px: np.ndarray):
    """The (my, mx) grid's corners with ``row_px`` added beyond ``side`` (0 left, 1 right, 2 top, 3 bottom)."""
    mx, my = grid_shape
    g = corners_px.reshape(my, mx, 2)
    if side < 2:
        col = row_px.reshape(my, 1, 2)
        g = np.concatenate([col, g] if side == 0 else [g, col], axis=1)
    else:
        row = row_px.reshape(1, mx, 2)
        g = np.concatenate([row, g] if side == 2 else [g, row], axis=0)
    return g.reshape(-1, 2), (g.shape[1], g.shape[0])


@dataclass(frozen=True)
class Colouring:
    """A board's checker colouring: ``phase`` (``checker_phase``) and the median ``contrast`` of its own corners
    (grey levels, ``checker_contrast``)."""

    phase: float
    contrast: float


def own_contrast(gray: np.ndarray, model: BoardModel, grid_shape: tuple[int, int]) -> tuple[float, np.ndarray]:
    """The board's colouring phase (``checker_phase``) and the checker contrast (mx·my,) of each of its own corners
    under it (grey levels, ``checker_contrast``), the board model mapping its (mx, my) grid."""
    own = grid_points(grid_shape)
    means = quadrant_means(gray, model, own)
    phase = checker_phase(means, own)
    return phase, checker_contrast(means, own, phase)


def colouring(gray: np.ndarray, model: BoardModel, grid_shape: tuple[int, int]) -> Colouring:
    """The colouring of the board whose corners the model maps, over its (mx, my) grid."""
    phase, clear = own_contrast(gray, model, grid_shape)
    return Colouring(phase, float(np.nanmedian(clear)))


def grow_once(
    gray: np.ndarray,
    corners_px: np.ndarray,
    grid_shape: tuple[int, int],
    side: int,
    model: Optional[BoardModel],
    colours: Colouring,
) -> Optional[np.ndarray]:
    """The (n, 2) px row of corners one beyond ``side`` (0 left, 1 right, 2 top, 3 bottom) of the grid, or None
    when the checker pattern does not run on there (see ``grow``); ``model`` the board model of the grid's corners."""
    row = _side_rows(grid_shape)[side]
    start = None if model is None else model.predict(row)
    if start is None or not np.isfinite(start).all():
        return None
    clear = checker_contrast(quadrant_means(gray, model, row), row, colours.phase)
    if not np.all(clear >= GROW_CONTRAST * colours.contrast):  # first: it fails where most sides stop
        return None
    refined = subpix(gray, start, half_window(corner_spacing(corners_px, grid_shape)))
    moved = np.linalg.norm(refined - start, axis=1)
    return refined if np.all(moved <= tolerance_px(ACCEPT_TOLERANCE, corners_px, grid_shape)) else None


def grow(
    gray: np.ndarray, corners_px: np.ndarray, pattern: tuple[int, int], k: tuple[float, float]
) -> tuple[np.ndarray, tuple[int, int]]:
    """The board's corners and grid (mx, my), grown row by row on each side while the checker pattern runs on;
    ``k`` the distortion (k1, k2) of its board model (``Refined.k``), kept as the grid grows.

    A side grows when every corner one row beyond it (where the board model puts it) refines within
    ACCEPT_TOLERANCE of that place, with its window inside the image, and is a corner of the board's
    colouring at least GROW_CONTRAST times as clear as the board's own corners (median). Past a fold the
    next row lies on the other board's plane, away from where this board's model puts it: growth stops."""
    size = (gray.shape[1], gray.shape[0])
    model = fit_model(corners_px, pattern, size, k)
    colours = colouring(gray, model, pattern) if model is not None else Colouring(1.0, 0.0)
    grid_shape = pattern
    if not colours.contrast > 0:
        return corners_px, grid_shape
    for side in range(4):
        while (row := grow_once(gray, corners_px, grid_shape, side, model, colours)) is not None:
            corners_px, grid_shape = _add_row(corners_px, grid_shape, side, row)
            model = fit_model(corners_px, grid_shape, size, k)
            if side in (0, 2):  # a row before the first: every corner's i + j, so the phase, changes parity
                colours = Colouring(-colours.phase, colours.contrast)
    return corners_px, grid_shape
