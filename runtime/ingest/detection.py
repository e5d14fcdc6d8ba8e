"""Finding the rig's boards in one photo: detect on a reduced copy, refine at native resolution, report each outcome.

Plain checkerboards, a cascade of detector STEPS on one copy reduced to about DETECT_WIDTH_PX wide,
padded with a white border (so that a board whose outer squares the image edge cuts is still found):
for every step in turn (the classic detector, then OpenCV's SB detector in its normalising and
exhaustive modes, slow when they find nothing), each pattern is searched while boards of it are left
to find (found, masked out with grey in the copy, searched again), until SEARCH_UNTIL boards are
kept: enough to tell them apart and know the camera, which then says where the others are. Every
board found is refined at native resolution and tested against its model, then its grid is grown
where the pattern runs on past it (``refine``); a board that fails is dropped with the reason.
Identical plain boards are told apart later (``identity``); here each detection only gets a
canonical handedness (board x, y appear like image x, y).

With a rig of several boards, the pipeline hands the first board kept to a placer
(``placement.place``): a camera of that one board says where the others are, and ``confirm`` looks
for each there with no detector call, its corners refined from where they are put; when it finds
them the search ends there. For that first board, SEED_STEPS come before STEPS: the classic
detector without its adaptive threshold (it fails in tens of ms where the adaptive one takes
hundreds) and the SB detector with ``LARGER``, asked for the shorter side squared on a copy about
SEED_WIDTH_PX wide, which returns any grid at least that large (one board of a rig whose boards meet
at folds, where the other modes find none); ``LARGER`` first on a rig whose boards meet (``seed_steps``).

Once the photo's camera is known, ``predicted.search_predicted`` looks again for the boards it shows in
view but that were not found.

ChArUco boards (``Board.aruco`` set) are found by their markers (``cv2.aruco.CharucoDetector``
on a copy about CHARUCO_WIDTH_PX wide, markers detected once per dictionary; its corners are refined at
native resolution with a window clear of the markers) and come out identified; a partly hidden
one keeps the corners found (the others NaN).

Pixels: x right, y down, origin at the centre of the top-left pixel; a point at x in a copy
reduced by an integer factor f (``INTER_AREA``) lies at f·(x + 0.5) − 0.5 natively.
Specified (with the measurements behind the steps) in models_spec/ingest.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import cv2
import numpy as np

from dimenet.runtime.formats.rig import Board, Rig, charuco_board
from dimenet.runtime.geometry import rescaled_px
from dimenet.runtime.ingest.grid import canonical, corner_spacing, fit_model, grid_points, residuals
from dimenet.runtime.ingest.refine import (
    GROW_CONTRAST,
    SUBPIX_WINDOW_FRACTION,
    SUBPIX_WINDOW_PX,
    grow,
    own_contrast,
    refine,
    refine_plain,
    subpix,
    tolerance_px,
)

DETECT_WIDTH_PX = 1008  # width of the reduced copy searched for plain boards (1/4 of 12 MP, 1/2 of 2 MP)
SEED_WIDTH_PX = 544  # width of the reduced copy the LARGER seed step searches (1/3 of 2 MP)
CHARUCO_WIDTH_PX = 2016  # width of the reduced copy searched for ChArUco markers
PAD_PX = 20  # white border added around each reduced copy
MASK_MARGIN_SQUARES = 1.0  # the mask reaches this far beyond a board's grid (its outer squares)
MASK_GREY = 128
SEARCH_UNTIL = 2  # the search over the whole photo stops when this many boards are kept (enough to identify them)
MIN_CHARUCO_CORNERS = 4  # a ChArUco board counts as found with at least this many corners
CHARUCO_TOLERANCE = 0.05  # a ChArUco corner off its board model by more than this fraction of the spacing is dropped
PLACE_TOLERANCE = 0.35  # a corner looked for where a camera puts it may lie this fraction of the spacing from there
CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
FLAG_NAMES = {
    "classic": {
        cv2.CALIB_CB_ADAPTIVE_THRESH: "ADAPTIVE_THRESH",
        cv2.CALIB_CB_NORMALIZE_IMAGE: "NORMALIZE_IMAGE",
        cv2.CALIB_CB_FAST_CHECK: "FAST_CHECK",
    },
    "sb": {
        cv2.CALIB_CB_NORMALIZE_IMAGE: "NORMALIZE_IMAGE",
        cv2.CALIB_CB_EXHAUSTIVE: "EXHAUSTIVE",
        cv2.CALIB_CB_LARGER: "LARGER",
    },
}


@dataclass(frozen=True)
class Step:
    """One detector call: ``cv2.findChessboardCorners`` (``classic``) or
    ``cv2.findChessboardCornersSB`` (``sb``) with ``flags``; with LARGER, asked for the pattern's shorter side
    squared, it returns any grid at least that large."""

    detector: str
    flags: int = 0
    width_px: int = DETECT_WIDTH_PX  # the whole photo is searched on a copy reduced to about this wide

    def describe(self, factor: int) -> str:
        """E.g. ``findChessboardCornersSB(NORMALIZE_IMAGE) at 1/2 size``."""
        names = [n for f, n in FLAG_NAMES[self.detector].items() if self.flags & f]
        call = "findChessboardCorners" if self.detector == "classic" else "findChessboardCornersSB"
        return f"{call}({'|'.join(names) or '0'})" + ("" if factor == 1 else f" at 1/{factor} size")


STEPS = (  # in order: cheapest and most finding first (models_spec/ingest.md, "Detector steps")
    Step("classic", CLASSIC_FLAGS),
    Step("sb", cv2.CALIB_CB_NORMALIZE_IMAGE),
    Step("sb", 0),
    Step("sb", cv2.CALIB_CB_EXHAUSTIVE),
    Step("sb", cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE),
)
SEED_STEPS = (  # before STEPS when a first board can place the others (models_spec/ingest.md, "Placing")
    Step("classic", cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK),
    Step("sb", cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_LARGER, SEED_WIDTH_PX),
)
MEET_SQUARES = 2.0  # two boards meet when inner corners of theirs lie this many squares apart or less


@dataclass(frozen=True)
class Detection:
    """One board kept: ``corners_px`` (mx·my, 2) native px row by row over its ``grid`` (mx, my), which is its
    ``pattern`` (nx, ny) or larger where it was grown at a fold (NaN: not found, ChArUco only); ``board`` its
    rig board index when its markers tell it (ChArUco), else None. ``found_by``: the detector step;
    ``residual_px`` its largest corner residual under the board model, ``tolerance_px`` what it may be."""

    pattern: tuple[int, int]
    corners_px: np.ndarray
    board: Optional[int] = None
    grid: Optional[tuple[int, int]] = None  # None: the pattern
    found_by: str = ""
    residual_px: float = float("nan")
    tolerance_px: float = float("nan")
    k: tuple[float, float] = (0.0, 0.0)  # the distortion (k1, k2) of its board model (``grid.BoardModel``)

    @property
    def grid_shape(self) -> tuple[int, int]:
        return self.pattern if self.grid is None else self.grid


@dataclass(frozen=True)
class Dropped:
    """A board a detector found and the refinement dropped: its ``pattern``, the step, and why."""

    pattern: tuple[int, int]
    found_by: str
    reason: str
    residual_px: float
    tolerance_px: float


@dataclass(frozen=True)
class BoardSearch:
    """The boards kept (ChArUco first, then plain ones in the order found) and those dropped; ``hidden``: rig
    boards looked for where the photo's camera puts them and not found, with what the look saw there."""

    detections: tuple[Detection, ...]
    dropped: tuple[Dropped, ...] = ()
    hidden: tuple[tuple[int, str], ...] = ()


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
    return rescaled_px(np.asarray(points, np.float64).reshape(-1, 2) - PAD_PX, factor)


def to_reduced(points: np.ndarray, factor: int) -> np.ndarray:
    """Native px (n, 2) -> the padded reduced copy's px."""
    return rescaled_px(points, 1.0 / factor) + PAD_PX


def outline(
    corners_px: np.ndarray,
    grid: tuple[int, int],
    margin: float,
    image_size: tuple[int, int],
    k: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """(4, 2) px the grid's outline ``margin`` squares beyond its outer corners (board model of the corners,
    distortion ``k`` = (k1, k2))."""
    mx, my = grid
    box = np.array([[-margin, -margin], [mx - 1 + margin, -margin], [mx - 1 + margin, my - 1 + margin]])
    box = np.vstack([box, [-margin, my - 1 + margin]])
    model = fit_model(corners_px, grid, image_size, k)
    out = model.predict(box) if model is not None else np.full((4, 2), np.nan)
    if not np.isfinite(out).all():  # the distortion has no inverse that far out: the homography alone
        found = np.isfinite(corners_px).all(1)
        H = cv2.findHomography(grid_points(grid)[found], corners_px[found], 0)[0]
        out = cv2.perspectiveTransform(box.reshape(-1, 1, 2), H).reshape(4, 2)
    return out


def mask(
    copy: np.ndarray,
    factor: int,
    corners_px: np.ndarray,
    grid: tuple[int, int],
    size: tuple[int, int],
    origin: tuple[int, int] = (0, 0),
    k: tuple[float, float] = (0.0, 0.0),
) -> None:
    """Fill the grid's printed pattern (native corners of a (width, height) image; board model distortion
    ``k``) with grey in the padded copy, reduced by ``factor``, of the image region whose top-left pixel is
    ``origin`` (x, y)."""
    quad = to_reduced(outline(corners_px, grid, MASK_MARGIN_SQUARES, size, k) - origin, factor)
    cv2.fillConvexPoly(copy, np.round(quad).astype(np.int32), MASK_GREY)


def find_one(copy: np.ndarray, pattern: tuple[int, int], step: Step) -> Optional[tuple[np.ndarray, tuple[int, int]]]:
    """The (mx·my, 2) corners (the copy's px) of one board found by ``step`` and its grid (mx, my): the
    ``pattern`` (nx, ny), or with LARGER any grid of at least its shorter side squared; None when nothing is
    found."""
    if step.detector == "classic":
        ok, corners = cv2.findChessboardCorners(copy, pattern, flags=step.flags)
        return (corners.reshape(-1, 2), pattern) if ok else None
    if step.flags & cv2.CALIB_CB_LARGER:
        side = min(pattern)
        ok, corners, meta = cv2.findChessboardCornersSBWithMeta(copy, (side, side), flags=step.flags)
        return (corners.reshape(-1, 2), (meta.shape[1], meta.shape[0])) if ok else None
    ok, corners = cv2.findChessboardCornersSB(copy, pattern, flags=step.flags)
    return (corners.reshape(-1, 2), pattern) if ok else None


def settle(
    gray: np.ndarray,
    corners_px: np.ndarray,
    pattern: tuple[int, int],
    found_by: str,
    found_grid: Optional[tuple[int, int]] = None,
):
    """A plain board found at ``corners_px`` (native, unrefined) over ``found_grid`` (the ``pattern`` when None;
    larger where the detector may return more): a Detection (refined, canonical, grown) or a Dropped with the
    reason."""
    found_grid = pattern if found_grid is None else found_grid
    refined = refine_plain(gray, corners_px, found_grid)
    if refined.corners_px is None:
        return Dropped(pattern, found_by, refined.reason, refined.residual_px, refined.tolerance_px)
    corners, grid = grow(gray, canonical(refined.corners_px, found_grid), found_grid, refined.k)
    return Detection(
        pattern,
        corners,
        grid=None if grid == pattern else grid,
        found_by=found_by,
        residual_px=refined.residual_px,
        tolerance_px=refined.tolerance_px,
        k=refined.k,
    )


@dataclass(frozen=True)
class Look:
    """A plain board looked for where a camera puts its corners (``look``): each corner (n, 2) px refined from
    there, whether it is ``confirmed`` (n,) (refined within PLACE_TOLERANCE of the spacing of where it was put, a
    checker corner at least GROW_CONTRAST times the reference contrast clear) and whether it is ``hidden`` (n,)
    (its four squares there do not separate into the checker's two colours: no corner of this board's pattern)."""

    corners_px: np.ndarray
    confirmed: np.ndarray
    hidden: np.ndarray


def look(
    gray: np.ndarray, predicted_px: np.ndarray, pattern: tuple[int, int], k: tuple[float, float], contrast: float
) -> Look:
    """A plain board looked for, with no detector, where a camera puts its corners (``predicted_px`` (nx·ny, 2)
    native px; ``k`` the lens (k1, k2) of a board model; ``contrast`` the reference, grey levels): see ``Look``.
    Each corner is refined from there (``refine.subpix``) with a ``cv2.cornerSubPix`` half-window of that
    tolerance, wider than ``refine``'s (at most SUBPIX_WINDOW_PX[1]): a corner put 15 px off at 12 MP must lie
    inside it, or it does not move and is kept where it was put. The squares are sampled about the board model
    of the corners refined within the tolerance (the others where they were put)."""
    reach = PLACE_TOLERANCE * corner_spacing(predicted_px, pattern)
    refined = subpix(gray, predicted_px, max(SUBPIX_WINDOW_PX[0], int(np.ceil(reach))))  # the window holds the corner
    moved = np.linalg.norm(refined - predicted_px, axis=1) <= reach
    model = fit_model(np.where(moved[:, None], refined, predicted_px), pattern, (gray.shape[1], gray.shape[0]), k)
    n = len(predicted_px)
    if model is None:
        return Look(refined, np.zeros(n, bool), np.zeros(n, bool))
    _, clear = own_contrast(gray, model, pattern)
    return Look(refined, moved & (clear >= GROW_CONTRAST * contrast), clear <= 0)


def confirm(
    gray: np.ndarray, predicted_px: np.ndarray, pattern: tuple[int, int], k: tuple[float, float], contrast: float
) -> Optional[np.ndarray]:
    """The corners (nx·ny, 2) px of a plain board looked for where a camera puts them (``look``) when every one is
    confirmed; else None. (Not yet judged: ``settle``.)"""
    seen = look(gray, predicted_px, pattern, k, contrast)
    return seen.corners_px if seen.confirmed.all() else None


def plain_patterns(rig: Rig) -> dict[tuple[int, int], int]:
    """Number of plain (no ArUco) boards of each (nx, ny) pattern in the rig."""
    counts: dict[tuple[int, int], int] = {}
    for b in rig.boards:
        if b.aruco is None:
            counts[b.inner_corners] = counts.get(b.inner_corners, 0) + 1
    return counts


def of_pattern(items, pattern: tuple[int, int]) -> int:
    """How many of the detections (or dropped boards) are of ``pattern``."""
    return sum(d.pattern == pattern for d in items)


Placer = Callable[[Detection], tuple[Detection, ...]]  # a board kept -> the boards found where its camera puts them


def search_plain(
    gray: np.ndarray,
    wanted: dict[tuple[int, int], int],
    steps: tuple[Step, ...],
    until: int,
    place: Optional[Placer] = None,
    known: tuple[Detection, ...] = (),
) -> tuple[list[Detection], list[Dropped]]:
    """Plain boards in ``gray``, each step on a padded copy reduced to about its ``width_px`` (``known`` boards and
    every board found masked out of every copy): at most ``wanted`` boards of each pattern, by each of ``steps``
    in turn, until ``until`` boards are kept; with ``place``, the first board kept is handed to it and, when it
    finds any, the search ends there."""
    size = (gray.shape[1], gray.shape[0])
    copies: dict[int, np.ndarray] = {}
    masked: list[tuple[np.ndarray, tuple[int, int], tuple[float, float]]] = []

    def copy_at(factor: int) -> np.ndarray:
        if factor not in copies:
            copies[factor] = reduce(gray, factor)
            for corners, grid, k in masked:
                mask(copies[factor], factor, corners, grid, size, k=k)
        return copies[factor]

    def mask_out(corners: np.ndarray, grid: tuple[int, int], k: tuple[float, float] = (0.0, 0.0)) -> None:
        masked.append((corners, grid, k))
        for factor, copy in copies.items():
            mask(copy, factor, corners, grid, size, k=k)

    for d in known:
        mask_out(d.corners_px, d.grid_shape, d.k)
    kept: list[Detection] = []
    dropped: list[Dropped] = []
    for step in steps:
        factor = reduction(gray.shape, step.width_px)
        for pattern, count in sorted(wanted.items()):
            while len(kept) < until and of_pattern(kept, pattern) < count and of_pattern(dropped, pattern) < count:
                found = find_one(copy_at(factor), pattern, step)
                if found is None:
                    break
                native, grid = to_native(found[0], factor), found[1]
                mask_out(native, grid)  # never found twice, kept or not
                outcome = settle(gray, native, pattern, step.describe(factor), grid)
                if isinstance(outcome, Dropped):
                    dropped.append(outcome)
                    continue
                kept.append(outcome)
                if place is not None and len(kept) == 1 and (placed := place(outcome)):
                    return kept + list(placed), dropped
                mask_out(outcome.corners_px, outcome.grid_shape, outcome.k)
    return kept, dropped


def find_charuco(gray: np.ndarray, rig: Rig) -> dict[int, np.ndarray]:
    """Refined native corners (nx·ny, 2), NaN where not found (or off the board's model), of every ChArUco
    board with at least MIN_CHARUCO_CORNERS corners found, by rig board index."""
    boards = {k: b for k, b in enumerate(rig.boards) if b.aruco is not None}
    if not boards:
        return {}
    factor = reduction(gray.shape, CHARUCO_WIDTH_PX)
    small = reduce(gray, factor)
    size = (gray.shape[1], gray.shape[0])
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
        pattern = board.inner_corners
        off = residuals(native, fit_model(native, pattern, size), pattern) > tolerance_px(
            CHARUCO_TOLERANCE, native, pattern
        )
        native[off] = np.nan
        if np.isfinite(native[:, 0]).sum() >= MIN_CHARUCO_CORNERS:
            found[k] = native
    return found


def outer_corners(board: Board) -> np.ndarray:
    """(m, 3) mm the board's outermost inner corners in {W}: the first and last row and column of its grid."""
    nx, ny = board.inner_corners
    grid = board.points().reshape(ny, nx, 3)
    return np.concatenate([grid[0], grid[-1], grid[1:-1, 0], grid[1:-1, -1]])


def nearest_mm(a: np.ndarray, b: np.ndarray, rows: int = 256) -> float:
    """The smallest distance (mm) between points a (n, 3) and b (m, 3), ``rows`` of a at a time (bounded memory)."""
    return min(float(np.linalg.norm(a[k : k + rows, None] - b[None], axis=2).min()) for k in range(0, len(a), rows))


def boards_meet(rig: Rig) -> bool:
    """Whether two plain boards of the rig meet: outermost inner corners of theirs at most MEET_SQUARES squares
    (of the larger) apart in {W}, so their printed squares touch with no white margin between (at a fold, say).
    Only pairs whose corners' bounding boxes come that near are measured."""
    plain = [b for b in rig.boards if b.aruco is None]
    edges = [outer_corners(b) for b in plain]
    reach = np.array([MEET_SQUARES * b.square_mm for b in plain]) * (1 + 1e-9)
    lo, hi = np.array([e.min(0) for e in edges]).reshape(-1, 3), np.array([e.max(0) for e in edges]).reshape(-1, 3)
    for i in range(len(plain) - 1):
        r = np.maximum(reach[i], reach[i + 1 :])[:, None]
        near = np.all((lo[i + 1 :] - r <= hi[i]) & (lo[i] - r <= hi[i + 1 :]), axis=1)
        for j in i + 1 + np.flatnonzero(near):
            if nearest_mm(edges[i], edges[j]) <= max(reach[i], reach[j]):
                return True
    return False


def seed_steps(rig: Rig) -> tuple[Step, ...]:
    """SEED_STEPS, the SB ``LARGER`` step first for a rig whose boards meet (``boards_meet``): there the classic
    detector, which needs a margin around a board, fails in tens of ms for each pattern where ``LARGER`` finds
    a board with its fold row."""
    return SEED_STEPS[::-1] if boards_meet(rig) else SEED_STEPS


def detect_boards(gray: np.ndarray, rig: Rig, place: Optional[Placer] = None) -> BoardSearch:
    """Every board found in the native grey image (see the module doc): ChArUco ones identified (maybe
    partly), plain ones whole, canonical and grown, until SEARCH_UNTIL boards are kept; the plain ones
    dropped, with the reason. With ``place`` and no ChArUco board found, SEED_STEPS come first and the first
    plain board kept places the others (``search_plain``)."""
    detections = [Detection(rig.boards[k].inner_corners, c, k) for k, c in find_charuco(gray, rig).items()]
    patterns = plain_patterns(rig)
    if not patterns:
        return BoardSearch(tuple(detections))
    place = None if detections else place
    steps = STEPS if place is None else seed_steps(rig) + STEPS
    until = SEARCH_UNTIL - len(detections)
    kept, dropped = search_plain(gray, patterns, steps, until, place, tuple(detections))
    return BoardSearch(tuple(detections + kept), tuple(dropped))
