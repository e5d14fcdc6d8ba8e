"""Looking again for the plain boards the photo's camera shows in view but that were not found:
first where that camera puts them (``detection.look``, no detector), then, unless a board was kept
there, the detector steps on a crop around it (the boards kept masked out), reduced so that its
squares are about CROP_SPACING_PX; only the first step when the look found the board partly hidden.
Pixels as in ``detection``. Specified in models_spec/ingest.md, "Looking again"."""

from __future__ import annotations

from typing import Optional

import numpy as np

from dimenet.runtime.formats.rig import Board, Rig
from dimenet.runtime.ingest.detection import (
    PAD_PX,
    STEPS,
    BoardSearch,
    Detection,
    Dropped,
    Step,
    find_one,
    look,
    mask,
    outline,
    plain_patterns,
    reduce,
    settle,
    to_native,
)
from dimenet.runtime.ingest.grid import corner_spacing, fit_model
from dimenet.runtime.ingest.refine import colouring

CROP_SPACING_PX = 20  # a predicted board's crop is reduced so that its corner spacing is about this


CROP_MARGIN_SQUARES = 2.0
# A rough camera's crops (one plane's, ``wider``) run this many of the detector STEPS whatever the look saw:
# the exhaustive SB modes cost 0.1-0.5 s per crop that holds no board, and a rough camera has several.
ROUGH_STEPS = 3  # the crop reaches this far beyond the predicted inner corners


def crop_box(predicted_px: np.ndarray, pattern: tuple[int, int], size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) px, x1 and y1 exclusive: the image region CROP_MARGIN_SQUARES around a board's
    predicted corners (nx·ny, 2) px, clipped to the (width, height) image."""
    quad = outline(predicted_px, pattern, CROP_MARGIN_SQUARES, size)
    lo = np.floor(np.nanmin(np.vstack([quad, predicted_px]), 0)).astype(int)
    hi = np.ceil(np.nanmax(np.vstack([quad, predicted_px]), 0)).astype(int) + 1
    w, h = size
    return max(0, lo[0]), max(0, lo[1]), min(w, hi[0]), min(h, hi[1])


def on_kept(points_px: np.ndarray, kept: tuple[Detection, ...], size: tuple[int, int]) -> bool:
    """Whether any point (n, 2) px lies on a board kept (inside its grid's outline, ``outline``) in the
    (width, height) image."""
    for d in kept:
        quad = outline(d.corners_px, d.grid_shape, 0.0, size, d.k)
        edges, to_point = np.roll(quad, -1, axis=0) - quad, points_px[:, None, :] - quad[None]
        cross = edges[None, :, 0] * to_point[..., 1] - edges[None, :, 1] * to_point[..., 0]  # (n, 4)
        if np.any(np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)):
            return True
    return False


def crop_search(
    gray: np.ndarray,
    predicted_px: np.ndarray,
    board: Board,
    patterns: list[tuple[int, int]],
    steps: tuple[Step, ...],
    known: tuple[Detection, ...],
) -> Optional[Detection | Dropped]:
    """A plain board of any of ``patterns`` found by ``steps`` in turn on the crop around where a camera puts
    ``board``'s corners (``predicted_px`` (nx·ny, 2) native px; ``crop_box``), the ``known`` boards masked out,
    reduced so that its corner spacing is about CROP_SPACING_PX: settled (a Detection or a Dropped), or None
    (nothing found, or the crop too small)."""
    size = (gray.shape[1], gray.shape[0])
    x0, y0, x1, y1 = crop_box(predicted_px, board.inner_corners, size)
    if x1 - x0 < 2 * PAD_PX or y1 - y0 < 2 * PAD_PX:
        return None
    factor = max(1, round(corner_spacing(predicted_px, board.inner_corners) / CROP_SPACING_PX))
    copy = reduce(np.ascontiguousarray(gray[y0:y1, x0:x1]), factor)
    for d in known:
        mask(copy, factor, d.corners_px, d.grid_shape, size, (x0, y0), d.k)
    for step in steps:
        for pattern in patterns:
            found_one = find_one(copy, pattern, step)
            if found_one is not None:
                where = f"{step.describe(factor)} in a crop around where {board.name!r} should be"
                return settle(gray, to_native(found_one[0], factor) + [x0, y0], pattern, where, found_one[1])
    return None


def search_predicted(
    gray: np.ndarray,
    rig: Rig,
    kept: tuple[Detection, ...],
    predicted: dict[int, np.ndarray],
    rough: bool = False,
    crops: bool = True,
) -> BoardSearch:
    """Plain boards looked for where the photo's camera puts them: ``predicted`` (nx·ny, 2) native px by rig
    board index, of boards in view but not found. Each is first looked at there (``look``, with the lens and
    contrast of the first plain board kept) unless it lies on a board kept: when every corner is confirmed and
    the board is kept (``settle``), no detector is called. Otherwise detector steps run on a crop around it
    (``crop_box``) with the boards found masked out, reduced so that its corner spacing is about
    CROP_SPACING_PX, for every plain pattern of the rig (the camera may come from a labelling that is still
    wrong: what lies there may be another board); at most one board per crop. Every step, unless the look
    found the board partly hidden (some corners confirmed, some no checker corner: no detector finds it
    whole), when only the first runs (cheap, for a camera off by whole squares); a ``rough`` camera (one
    plane's: off by more than the look can tell from a hidden corner) runs the first ROUGH_STEPS there and
    everywhere; without ``crops``, only the looks. Returns the boards found
    (not yet identified; ``found_by`` says where), those dropped, and those not found where the look saw
    corners hidden (``BoardSearch.hidden``: how many)."""
    size = (gray.shape[1], gray.shape[0])
    patterns = sorted(plain_patterns(rig))
    reference = next((d for d in kept if d.board is None), None)
    model = None if reference is None else fit_model(reference.corners_px, reference.grid_shape, size, reference.k)
    contrast = float("nan") if model is None else colouring(gray, model, reference.grid_shape).contrast
    found: list[Detection] = []
    dropped: list[Dropped] = []
    hidden: list[tuple[int, str]] = []
    for b, px in sorted(predicted.items()):
        board = rig.boards[b]
        if board.aruco is not None:
            continue
        steps, seen = (STEPS[:ROUGH_STEPS] if rough else STEPS), None
        if np.isfinite(contrast) and not on_kept(px, (*kept, *found), size):
            seen = look(gray, px, board.inner_corners, reference.k, contrast)
            if seen.confirmed.all():
                where = f"refined where the photo's camera puts {board.name!r}"
                outcome = settle(gray, seen.corners_px, board.inner_corners, where)
                if isinstance(outcome, Detection):
                    found.append(outcome)
                    continue
            elif seen.hidden.any() and seen.confirmed.any() and not rough:
                steps = STEPS[:1]
        outcome = crop_search(gray, px, board, patterns, steps, (*kept, *found)) if crops else None
        if outcome is not None:
            (dropped if isinstance(outcome, Dropped) else found).append(outcome)
        elif seen is not None and seen.hidden.any():
            hidden.append((b, f"hidden: {int(seen.hidden.sum())} of {len(px)} corners are no checker corner there"))
    return BoardSearch(tuple(found), tuple(dropped), tuple(hidden))
