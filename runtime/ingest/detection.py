"""Finding the rig's boards in one photo: detect on reduced copies, refine at native resolution.

Plain checkerboards: ``cv2.findChessboardCorners`` on a copy reduced to about 1344 px wide (1/3
of a 12 MP photo), then on one about 1008 px wide (1/4), then ``cv2.findChessboardCornersSB`` on
the latter (the first that succeeds; the two fallbacks only while fewer than 2 boards are found,
unless ``thorough``: ``ingest`` asks for that when the rig says a board is in view but missing);
the found board is masked out (its printed pattern filled with grey in every copy) and the search
repeats until nothing more is found. The copies are
padded with a white border so that a board whose outer squares the image edge cuts is still
found. Each corner is then refined with ``cv2.cornerSubPix`` on the native grey image, with a
window scaled to the square size. A corner left off the board's grid (farther than a tolerance
from the homography of all corners) is started again where the other corners put it; a board
with a corner still off the grid, or whose window leaves the image, is dropped (the white border
can fake a row of corners along the image edge). Identical plain boards are told apart later
(``board_identity``); here each detection only gets a canonical handedness (board x, y appear
like image x, y: right-handed in a y-down image).

ChArUco boards (``Board.aruco`` set) are found by their markers (``cv2.aruco.CharucoDetector``
on a copy about 2016 px wide, markers detected once per dictionary; its corners are refined at
native resolution with a window clear of the markers) and come out identified; a partly hidden
one keeps the corners found (the others NaN).

Pixels: x right, y down, origin at the centre of the top-left pixel; a point at x in a copy
reduced by an integer factor f (``INTER_AREA``) lies at f·(x + 0.5) − 0.5 natively.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime.formats.rig import Board, Rig

DETECT_WIDTHS_PX = (1344, 1008)  # widths of the reduced copies searched for plain boards
CHARUCO_WIDTH_PX = 2016  # width of the reduced copy searched for ChArUco markers
PAD_PX = 20  # white border added around each reduced copy
CASCADE = ((0, "classic"), (1, "classic"), (1, "sector"))  # (DETECT_WIDTHS_PX index, detector), tried in order
FALLBACK_BELOW = 2  # the CASCADE's fallbacks are tried while fewer boards than this are found (unless thorough)
CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
MASK_MARGIN_SQUARES = 1.25  # the mask reaches this far beyond the inner corners (outer squares + paper)
MASK_GREY = 128
SUBPIX_WINDOW_FRACTION = 0.3  # cornerSubPix half-window as a fraction of the smallest corner spacing
SUBPIX_WINDOW_PX = (2, 12)  # clip of that half-window, native px
GRID_TOLERANCE = 0.05  # a refined plain-board corner lies within this fraction of the corner spacing
GRID_TOLERANCE_MIN_PX = 1.0  # (or this many px, if more) of the board's homography fitted to all its corners
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.001)
MIN_CHARUCO_CORNERS = 4  # a ChArUco board counts as found with at least this many corners


@dataclass(frozen=True)
class Detection:
    """One board found in a photo: (nx·ny, 2) native px corners, row by row (NaN: not found, ChArUco
    only), and its rig board index when the markers tell it (ChArUco), else None."""

    pattern: tuple[int, int]  # (nx, ny) inner corners
    corners_px: np.ndarray
    board: Optional[int] = None


def charuco_board(board: Board) -> cv2.aruco.CharucoBoard:
    """OpenCV's ChArUco board for a rig board with ``aruco`` (corner ids = the rig's corner order)."""
    a = board.aruco
    nx, ny = board.inner_corners
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, a.dictionary))
    n_markers = (nx + 1) * (ny + 1) // 2
    return cv2.aruco.CharucoBoard(
        (nx + 1, ny + 1), board.square_mm, a.marker_mm, dictionary, np.arange(a.first_id, a.first_id + n_markers)
    )


def reduction(shape: tuple[int, ...], width_px: int) -> int:
    """The integer factor that brings an image of ``shape`` (h, w) closest to ``width_px`` wide (>= 1)."""
    return max(1, round(max(shape[:2]) / width_px))


def reduce(gray: np.ndarray, factor: int) -> np.ndarray:
    """The grey image reduced by an integer ``factor`` (box filter), padded with PAD_PX of white."""
    h, w = gray.shape
    small = cv2.resize(gray, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    return cv2.copyMakeBorder(small, PAD_PX, PAD_PX, PAD_PX, PAD_PX, cv2.BORDER_CONSTANT, value=255)


def to_native(points: np.ndarray, factor: int) -> np.ndarray:
    """Points (n, 2) in a padded reduced copy -> native px."""
    return factor * (np.asarray(points, np.float64).reshape(-1, 2) - PAD_PX + 0.5) - 0.5


def to_reduced(points: np.ndarray, factor: int) -> np.ndarray:
    """Native px (n, 2) -> the padded reduced copy's px."""
    return (np.asarray(points, np.float64) + 0.5) / factor - 0.5 + PAD_PX


def grid_points(pattern: tuple[int, int]) -> np.ndarray:
    """(nx·ny, 2) the inner corners in grid units (i, j), row by row (j outer, i inner)."""
    nx, ny = pattern
    j, i = np.mgrid[0:ny, 0:nx]
    return np.stack([i.ravel(), j.ravel()], 1).astype(np.float64)


def grid_homography(corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """(3, 3) homography from grid units (i, j) to px, fitted to the (nx·ny, 2) corners (NaN rows ignored)."""
    grid = grid_points(pattern)
    found = np.isfinite(corners_px).all(1)
    return cv2.findHomography(grid[found], corners_px[found].astype(np.float64), 0)[0]


def pattern_outline(corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """(4, 2) px the board's outline MASK_MARGIN_SQUARES beyond its outer inner corners (perspective-exact)."""
    nx, ny = pattern
    margin = MASK_MARGIN_SQUARES
    box = np.array(
        [
            [[-margin, -margin]],
            [[nx - 1 + margin, -margin]],
            [[nx - 1 + margin, ny - 1 + margin]],
            [[-margin, ny - 1 + margin]],
        ]
    )
    return cv2.perspectiveTransform(box, grid_homography(corners_px, pattern)).reshape(4, 2)


def mask_board(copies: dict[int, np.ndarray], corners_px: np.ndarray, pattern: tuple[int, int]) -> None:
    """Fill the board's printed pattern (native corners) with grey in every reduced copy, in place."""
    outline = pattern_outline(corners_px, pattern)
    for factor, img in copies.items():
        cv2.fillConvexPoly(img, np.round(to_reduced(outline, factor)).astype(np.int32), MASK_GREY)


def cascade(shape: tuple[int, ...]) -> list[tuple[int, str]]:
    """The CASCADE for an image of ``shape`` (h, w) as (reduction factor, detector), repeats dropped."""
    return list(dict.fromkeys((reduction(shape, DETECT_WIDTHS_PX[k]), detector) for k, detector in CASCADE))


def find_one(
    copies: dict[int, np.ndarray], pattern: tuple[int, int], steps: list[tuple[int, str]]
) -> Optional[np.ndarray]:
    """Native px (nx·ny, 2) of one board found by the first of ``steps`` that succeeds, or None."""
    for factor, detector in steps:
        if detector == "classic":
            ok, corners = cv2.findChessboardCorners(copies[factor], pattern, flags=CLASSIC_FLAGS)
        else:
            ok, corners = cv2.findChessboardCornersSB(copies[factor], pattern, flags=0)
        if ok:
            return to_native(corners, factor)
    return None


def find_plain(
    copies: dict[int, np.ndarray],
    pattern: tuple[int, int],
    max_count: int,
    steps: list[tuple[int, str]],
    found_before: int,
    thorough: bool,
) -> list[np.ndarray]:
    """Up to ``max_count`` boards of one pattern (native px, unrefined): find one, mask it, repeat.

    The fallback ``steps`` (after the first) are tried only while fewer than FALLBACK_BELOW boards are
    found in all (``found_before`` of other patterns), or always when ``thorough``: they seldom find a
    board the first step missed, and they cost most when there is none left to find."""
    found: list[np.ndarray] = []
    while len(found) < max_count:
        fallbacks = thorough or found_before + len(found) < FALLBACK_BELOW
        corners = find_one(copies, pattern, steps if fallbacks else steps[:1])
        if corners is None:
            break
        found.append(corners)
        mask_board(copies, corners, pattern)
    return found


def corner_spacing(corners_px: np.ndarray, pattern: tuple[int, int]) -> float:
    """Smallest distance (px) between neighbouring corners found, along rows, columns and diagonals
    (inf when no two neighbours are found)."""
    nx, ny = pattern
    g = corners_px.reshape(ny, nx, 2)
    steps = [g[:, 1:] - g[:, :-1], g[1:] - g[:-1], g[1:, 1:] - g[:-1, :-1], g[1:, :-1] - g[:-1, 1:]]
    d = np.concatenate([np.linalg.norm(s, axis=-1).ravel() for s in steps])
    d = d[np.isfinite(d)]
    return float(d.min()) if d.size else float("inf")


def window_inside(corners_px: np.ndarray, half_px: int, shape: tuple[int, ...]) -> np.ndarray:
    """(n,) whether each corner's refinement window (``half_px`` each side, + 1 px) lies inside the image."""
    h, w = shape[:2]
    m = half_px + 1
    x, y = corners_px[:, 0], corners_px[:, 1]
    return (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)


def refine(
    gray: np.ndarray, corners_px: np.ndarray, pattern: tuple[int, int], window_fraction: float = SUBPIX_WINDOW_FRACTION
) -> np.ndarray:
    """Sub-pixel corners (nx·ny, 2) px on the native grey image (``cv2.cornerSubPix``).

    The half-window is ``window_fraction`` of the smallest corner spacing (clipped to SUBPIX_WINDOW_PX).
    NaN where a corner is missing or its window leaves the image.
    """
    lo, hi = SUBPIX_WINDOW_PX
    half = int(np.clip(window_fraction * corner_spacing(corners_px, pattern), lo, hi))
    inside = window_inside(corners_px, half, gray.shape)
    out = np.full(corners_px.shape, np.nan)
    if inside.any():
        pts = corners_px[inside].astype(np.float32).reshape(-1, 1, 2)
        out[inside] = cv2.cornerSubPix(gray, pts, (half, half), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2)
    out[~window_inside(out, half, gray.shape)] = np.nan
    return out


def grid_fit(corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """(nx·ny, 2) px every corner where the board's homography, fitted to the found (finite) corners, puts it;
    NaN when they fix no homography (fewer than 4, or collinear)."""
    grid = grid_points(pattern)
    if np.isfinite(corners_px[:, 0]).sum() < 4:
        return np.full_like(grid, np.nan)
    H = grid_homography(corners_px, pattern)
    return (
        np.full_like(grid, np.nan) if H is None else cv2.perspectiveTransform(grid.reshape(-1, 1, 2), H).reshape(-1, 2)
    )


def off_grid(corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """(nx·ny,) whether each corner lies farther than the grid tolerance from the homography fitted to all
    (missing corners, and every corner when there is no homography, count as off)."""
    tolerance = max(GRID_TOLERANCE_MIN_PX, GRID_TOLERANCE * corner_spacing(corners_px, pattern))
    return ~(np.linalg.norm(grid_fit(corners_px, pattern) - corners_px, axis=1) <= tolerance)


def refine_plain(gray: np.ndarray, corners_px: np.ndarray, pattern: tuple[int, int]) -> Optional[np.ndarray]:
    """A plain board's refined corners (nx·ny, 2) px, or None when it is not found whole.

    A corner left off the board's grid (the detector misplaced it, e.g. at the end of an oblique
    row, and cornerSubPix found no corner there) is started again from where the other corners'
    homography puts it. None when a corner's window leaves the image or a corner stays off the grid.
    """
    refined = refine(gray, corners_px, pattern)
    if not np.isfinite(refined).all():
        return None
    off = off_grid(refined, pattern)
    if off.any():
        start = np.where(off[:, None], grid_fit(np.where(off[:, None], np.nan, refined), pattern), refined)
        refined = refine(gray, start, pattern)
        if not np.isfinite(refined).all() or off_grid(refined, pattern).any():
            return None
    return refined


def canonical(corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """The corners reordered (rows reversed if needed) so that the grid is right-handed in the image.

    A board seen from its printed side shows its x (along a row) and y (down the columns) like
    the image's x and y: cross(x, y) > 0 in the y-down image.
    """
    nx, ny = pattern
    g = corners_px.reshape(ny, nx, 2)
    ex, ey = g[:, -1].mean(0) - g[:, 0].mean(0), g[-1].mean(0) - g[0].mean(0)
    return corners_px if ex[0] * ey[1] - ex[1] * ey[0] > 0 else g[::-1].reshape(-1, 2)


def grid_symmetries(pattern: tuple[int, int]) -> list[np.ndarray]:
    """Index permutations (n,) of the in-plane rotations that map the (nx, ny) grid onto itself.

    A right-handed detection of a plain board is known up to these: 0° and 180°, plus 90° and
    270° for a square grid. ``corners[perm]`` is the detection under that rotation.
    """
    nx, ny = pattern
    idx = np.arange(nx * ny).reshape(ny, nx)
    return [np.rot90(idx, k).ravel() for k in range(4) if np.rot90(idx, k).shape == idx.shape]


def find_charuco(gray: np.ndarray, rig: Rig) -> dict[int, np.ndarray]:
    """Refined native corners (nx·ny, 2), NaN where not found (or off the board's grid), of every ChArUco
    board with at least MIN_CHARUCO_CORNERS corners found, by rig board index."""
    boards = {k: b for k, b in enumerate(rig.boards) if b.aruco is not None}
    if not boards:
        return {}
    factor = reduction(gray.shape, CHARUCO_WIDTH_PX)
    small = reduce(gray, factor)
    markers = {}
    for name in sorted({b.aruco.dictionary for b in boards.values()}):
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        markers[name] = cv2.aruco.ArucoDetector(dictionary).detectMarkers(small)[:2]
    found = {}
    for k, board in boards.items():
        marker_corners, marker_ids = markers[board.aruco.dictionary]
        if marker_ids is None:
            continue
        corners, ids, _, _ = cv2.aruco.CharucoDetector(charuco_board(board)).detectBoard(
            small, markerCorners=marker_corners, markerIds=marker_ids
        )
        if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
            continue
        native = np.full((board.n_points, 2), np.nan)
        native[ids.ravel()] = to_native(corners.reshape(-1, 2), factor)
        if factor > 1:  # found on a reduced copy: refine at native resolution, the window clear of the markers
            clear_of_markers = (board.square_mm - board.aruco.marker_mm) / (2.0 * board.square_mm)
            native = refine(gray, native, board.inner_corners, min(SUBPIX_WINDOW_FRACTION, clear_of_markers))
        native[off_grid(native, board.inner_corners)] = np.nan
        if np.isfinite(native[:, 0]).sum() >= MIN_CHARUCO_CORNERS:
            found[k] = native
    return found


def plain_patterns(rig: Rig) -> dict[tuple[int, int], int]:
    """Number of plain (no ArUco) boards of each (nx, ny) pattern in the rig."""
    counts: dict[tuple[int, int], int] = {}
    for b in rig.boards:
        if b.aruco is None:
            counts[b.inner_corners] = counts.get(b.inner_corners, 0) + 1
    return counts


def detect_boards(gray: np.ndarray, rig: Rig, thorough: bool = False) -> list[Detection]:
    """Every board found in the native grey image: ChArUco ones identified (maybe partly), plain ones
    whole and canonical (a plain board with a corner too near the image edge or off its grid is left out).

    ``thorough``: try the CASCADE's fallbacks for every board, not only until FALLBACK_BELOW are found."""
    detections = [Detection(rig.boards[k].inner_corners, c, k) for k, c in find_charuco(gray, rig).items()]
    patterns = plain_patterns(rig)
    if not patterns:
        return detections
    steps = cascade(gray.shape)
    copies = {f: reduce(gray, f) for f, _ in steps}
    for d in detections:
        mask_board(copies, d.corners_px, d.pattern)
    for pattern, count in sorted(patterns.items()):
        for corners in find_plain(copies, pattern, count, steps, len(detections), thorough):
            refined = refine_plain(gray, corners, pattern)
            if refined is not None:
                detections.append(Detection(pattern, canonical(refined, pattern)))
    return detections
