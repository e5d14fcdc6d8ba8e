"""Where a camera puts the rig's boards: which are in view, and the others found from the first board alone.

One board found is one plane: with square pixels and the principal point at the image centre, its
homography gives the focal length (``geometry.planar_focal``, within a few % on real photos), and a
PnP of it, as each rig board it may be (``identity.candidates``; the largest first: a grid larger than
its pattern is likelier a board and a fold row than a smaller board and two), a camera that puts every other
board within about a quarter of a square (models_spec/ingest.md, "Placing"). Where that camera shows
plain boards in view, their corners are refined from there with no detector call
(``detection.confirm``). Once a second board is confirmed, the rest are looked for under two cameras of both
boards: the one-plane K held (a PnP), then K refitted free (``identity.refit``, which also tells a wrong
hypothesis: no one camera puts both boards there); on two planes a free K can put a third board further
off than the held one (models_spec/ingest.md, "Looking wider"). The first hypothesis under which every
board in view is confirmed and kept (``detection.settle``) gives them. A wrong hypothesis puts boards on
the desk, on the boards' margins or across a fold, where the corners do not refine, are no checker
corners or do not fit one board.

Pixels: x right, y down; 3D in mm in the rig frame {W}; poses {W}->{C}.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.rig import Rig
from dimenet.runtime.geometry import (
    camera_centre,
    facing,
    k_matrix,
    planar_focal,
    project,
    project_camera,
    solve_pnp_start,
    to_camera,
)
from dimenet.runtime.ingest.detection import PLACE_TOLERANCE, Detection, confirm, settle
from dimenet.runtime.ingest.grid import corner_spacing, fit_model
from dimenet.runtime.ingest.identity import candidates, refit, rough_k
from dimenet.runtime.ingest.refine import colouring

PLACE_AGREEING = 2  # a hypothesis holds when every plain board it shows in view is confirmed, or this many
IN_VIEW_MARGIN_PX = 4.0  # a board is looked for where the camera puts it when its corners lie this far inside the image


def boards_in_view(
    rig: Rig, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, image_size: tuple[int, int]
) -> np.ndarray:
    """(B,) whether each rig board, seen by the camera (K px, pose {W}->{C}), lies in front of it, faces it
    and has every corner at least IN_VIEW_MARGIN_PX inside the (width, height) image."""
    w, h = image_size
    points = rig.points()
    points_cam = to_camera(points, rvec, tvec)
    px = project_camera(K, points_cam)
    inside = np.all((px >= IN_VIEW_MARGIN_PX) & (px <= np.array([w - 1, h - 1]) - IN_VIEW_MARGIN_PX), axis=1)
    first = np.r_[0, np.cumsum([b.n_points for b in rig.boards])[:-1]]
    seen = np.logical_and.reduceat(inside & (points_cam[:, 2] > 0), first)
    normals = np.array([b.normal() for b in rig.boards])
    return seen & facing(points[first], -normals, camera_centre(rvec, tvec))


def one_plane_k(H: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(3, 3) px the K one board's homography H (grid units -> undistorted px) gives (square pixels, centred;
    ``planar_focal``), or the rough K (``identity.rough_k``) where it tells no focal length (seen face on)."""
    K = rough_k(image_size)
    f = planar_focal(H, K[:2, 2])
    return K if not np.isfinite(f) else k_matrix([f, f, K[0, 2], K[1, 2]])


def nearest_first(boards: list[int], rig: Rig, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, seed_px) -> list:
    """The rig ``boards`` ordered by how far the camera puts their centre from the mean of ``seed_px`` (px)."""
    centre = np.nanmean(seed_px, axis=0)
    far = [np.linalg.norm(project(rig.boards[b].points(), K, rvec, tvec).mean(0) - centre) for b in boards]
    return [boards[i] for i in np.argsort(far, kind="stable")]


def place(gray: np.ndarray, rig: Rig, seed: Detection) -> tuple[Detection, ...]:
    """The plain boards found where a camera of the one board ``seed`` puts them (see the module doc); () when no
    hypothesis about it confirms one."""
    size = (gray.shape[1], gray.shape[0])
    model = fit_model(seed.corners_px, seed.grid_shape, size, seed.k)
    if model is None:
        return ()
    contrast = colouring(gray, model, seed.grid_shape).contrast
    K = one_plane_k(model.H, size)
    points = rig.points()
    tolerance = PLACE_TOLERANCE * corner_spacing(seed.corners_px, seed.grid_shape)

    def plain_in_view(K, rvec, tvec, known) -> list[int]:
        in_view = boards_in_view(rig, K, rvec, tvec, size)
        return [b for b in np.flatnonzero(in_view) if b not in known and rig.boards[b].aruco is None]

    def look(b: int, K, rvec, tvec) -> Optional[np.ndarray]:
        board = rig.boards[b]
        return confirm(gray, project(board.points(), K, rvec, tvec), board.inner_corners, seed.k, contrast)

    for c in sorted(candidates(seed, rig), key=lambda c: -len(c.rig_index)):  # the largest boards first
        try:
            rvec, tvec = solve_pnp_start(c.corners_px, points[c.rig_index], K)
        except InputError:
            continue
        others = nearest_first(plain_in_view(K, rvec, tvec, {c.board}), rig, K, rvec, tvec, seed.corners_px)
        first = look(others[0], K, rvec, tvec) if others else None
        if first is None:
            continue
        board = rig.boards[others[0]]
        p2 = [np.vstack([c.corners_px, first])]
        p3 = [np.vstack([points[c.rig_index], board.points()])]
        rms, fit = refit(p2, p3, K, rvec[None], tvec[None])
        if not rms[0] <= tolerance:  # no one camera puts both boards there: a wrong hypothesis
            continue
        try:  # the first K held, posed on both boards: a K freed on two planes can put a third further off
            held = (K, *solve_pnp_start(p2[0], p3[0], K))
        except InputError:
            continue
        found, rest = {others[0]: first}, set()
        for camera in (held, (fit.K[0], fit.rvec[0], fit.tvec[0])):
            for b in plain_in_view(*camera, {c.board} | found.keys()):
                rest.add(b)
                if (px := look(b, *camera)) is not None:
                    found[b] = px
        if len(found) < min(len(rest) + 1, PLACE_AGREEING):  # a board this camera shows is not there
            continue
        name = rig.boards[c.board].name
        where = f"refined where the first board's camera (as {name!r}) puts it"
        kept = [settle(gray, px, rig.boards[b].inner_corners, where) for b, px in found.items()]
        if all(isinstance(d, Detection) for d in kept):
            return tuple(kept)
    return ()
