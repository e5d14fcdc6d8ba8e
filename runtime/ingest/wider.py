"""Looking wider when the boards found cannot fix the photo's camera or tell which boards they are.

Identical plain boards found two at a time may lie in one plane (no K from them: a CalibrationError),
or fit several labellings alike (``identity.ambiguous``); either way no one camera says where the
boards not found are, and the photo was skipped with boards of the rig in full view. Here every camera
the boards found allow is asked where it puts the others, which are looked for there
(``predicted.search_predicted``: a look, then the detector steps on a crop, the boards kept masked
out): a board found under a wrong camera is still a board, and ``identity.label`` on all of them
tells the labellings apart. Specified in models_spec/ingest.md, "Looking again".

Pixels: x right, y down; 3D in mm in the rig frame {W}; poses {W}->{C}.
"""

from __future__ import annotations

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.rig import Rig
from dimenet.runtime.geometry import project, solve_pnp_start
from dimenet.runtime.ingest.detection import BoardSearch
from dimenet.runtime.ingest.grid import fit_model
from dimenet.runtime.ingest.identity import Identification, ambiguous, candidates
from dimenet.runtime.ingest.placement import boards_in_view, one_plane_k
from dimenet.runtime.ingest.predicted import on_kept, search_predicted


def look_where(gray: np.ndarray, rig: Rig, search: BoardSearch, cameras, rough: bool = False) -> BoardSearch:
    """``search`` with the boards found where each of ``cameras`` ((K, rvec, tvec) each) puts the rig boards it
    shows in view, off the boards kept (``search_predicted``, its ``rough`` steps for rough cameras; the boards
    found so far masked out), until one more board is found: with it the photo's own camera, or labelling,
    says where the rest are (``pipeline.find_and_label``), cheaper than the next camera's crops."""
    size = (gray.shape[1], gray.shape[0])
    until = len(search.detections) + 1
    views = [(camera, np.flatnonzero(boards_in_view(rig, *camera, size))) for camera in cameras]
    # The cameras that show more of the rig first (the photo was taken of it); every camera's looks (no
    # detector call, a few ms) before any crop search (tens to hundreds of ms each).
    ordered = sorted(views, key=lambda v: -len(v[1]))
    for crops in (False, True):
        for (K, rvec, tvec), in_view in ordered:
            if len(search.detections) >= until:
                return search
            predicted = {}
            for b in in_view:
                px = project(rig.boards[b].points(), K, rvec, tvec)
                if not on_kept(px, search.detections, size):
                    predicted[int(b)] = px
            if not predicted:
                continue
            again = search_predicted(gray, rig, search.detections, predicted, rough, crops)
            search = BoardSearch(search.detections + again.detections, search.dropped + again.dropped, search.hidden)
    return search


def look_under_close_labellings(gray: np.ndarray, rig: Rig, found: Identification, search: BoardSearch):
    """While the labelling is ambiguous and boards are missing: where the camera of each labelling as good as
    the winner (``Identification.close``) puts the others (``look_where``)."""
    if not ambiguous(found) or len(search.detections) >= len(rig.boards):
        return search
    return look_where(gray, rig, search, found.close)


def look_from_one_plane(gray: np.ndarray, rig: Rig, search: BoardSearch) -> BoardSearch:
    """Boards found all in one plane give no K, but the first one's homography gives a focal length
    (``placement.one_plane_k``) and a pose as each board and turn it may be (``identity.candidates``): where
    each such camera, rough as it is, puts the others (``look_where``)."""
    seed = search.detections[0]
    size = (gray.shape[1], gray.shape[0])
    model = fit_model(seed.corners_px, seed.grid_shape, size, seed.k)
    if model is None:
        return search
    K = one_plane_k(model.H, size)
    points = rig.points()
    cameras = []
    for c in candidates(seed, rig):
        try:
            cameras.append((K, *solve_pnp_start(c.corners_px, points[c.rig_index], K)))
        except InputError:
            continue
    return look_where(gray, rig, search, cameras, rough=True)
