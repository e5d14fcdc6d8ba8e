"""Telling a photo's boards apart: which rig board, turned which way, each detection is.

ChArUco detections come identified by their markers. Plain boards of one pattern are
identical, so a detection may be any of them, turned by any symmetry of its grid (0° or
180°; 90° and 270° too for a square grid): a *labelling* gives every detection one
(board, turn), each board at most once.

1. Seeds: every labelling of the first detections (identified ones first; two detections, or
   one when labelled natural points are known too). A PnP (SQPnP) with a rough K on the seed's
   corners fixes the camera (two boards lie on different planes); every other detection takes
   the free (board, turn) whose projected corners lie closest (RMS px).
2. Every distinct completed labelling is scored by the reprojection RMS (px) of a PnP with the
   rough K on all the photo's points; the TOP_N best are refitted with a free K (the
   single-frame calibration: LM over K and pose, ``least_squares.fit``, from the rough K and
   the PnP pose).
3. The best refit wins when the next one leaves at least AMBIGUITY_RATIO times its RMS;
   otherwise the photo is ambiguous (e.g. a rig that looks nearly the same turned round).

Pixels: x right, y down; 3D in mm in the rig frame {W}.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from dimenet.runtime.errors import CalibrationError, IdentificationError, InputError
from dimenet.runtime.formats.rig import Rig
from dimenet.runtime.geometry import k_matrix, least_squares, project, reprojection_errors, solve_pnp_start
from dimenet.runtime.geometry.spread import RIG_VIEW_RATIO, spans_3d
from dimenet.runtime.ingest.detection import Detection, grid_symmetries

ROUGH_FOCAL = 0.75  # rough focal length / the image's longer side: a phone's main camera (≈ 26 mm equivalent)
TOP_N = 4  # labellings refitted with a free K
AMBIGUITY_RATIO = 3.0  # the runner-up's refit RMS must be at least this multiple of the winner's


@dataclass(frozen=True)
class Identification:
    """The winning labelling of a photo's detections and the photo's best single-frame K."""

    corners_px: np.ndarray  # (P, 2) px: every rig corner in rig order, NaN where not found
    boards: tuple[int, ...]  # rig board index of each detection, in detection order
    K: np.ndarray  # (3, 3) px: K fitted with the pose on all the photo's points
    rvec: np.ndarray  # (3,) rad and
    tvec: np.ndarray  # (3,) mm: that pose {W}->{C}
    rms_px: float  # reprojection RMS (px) under K
    runner_up_rms_px: float  # the same for the next-best labelling; inf when there is none


def rough_k(image_size: tuple[int, int]) -> np.ndarray:
    """(3, 3) px a rough K for a (width, height) image: ROUGH_FOCAL x the longer side, centred."""
    w, h = image_size
    f = ROUGH_FOCAL * max(w, h)
    return k_matrix([f, f, (w - 1) / 2.0, (h - 1) / 2.0])


@dataclass(frozen=True)
class Options:
    """The (board, turn) candidates of one detection: ``corners_px`` (C, n, 2) px its corners in each
    candidate's board order, ``rig_index`` (C, n) the rig corner (row of ``Rig.points()``) of each."""

    board: np.ndarray  # (C,) rig board index
    corners_px: np.ndarray
    rig_index: np.ndarray


def options(detection: Detection, rig: Rig) -> Options:
    """A detection's candidates: its own board when identified, else every plain board of its pattern
    under every symmetry of its grid."""
    start = np.r_[0, np.cumsum([b.n_points for b in rig.boards])]
    if detection.board is not None:
        pairs = [(detection.board, np.arange(len(detection.corners_px)))]
    else:
        pairs = [
            (b, perm)
            for b, board in enumerate(rig.boards)
            if board.aruco is None and board.inner_corners == detection.pattern
            for perm in grid_symmetries(detection.pattern)
        ]
    return Options(
        board=np.array([b for b, _ in pairs]),
        corners_px=np.stack([detection.corners_px[p] for _, p in pairs]),
        rig_index=np.stack([start[b] + np.arange(len(p)) for b, p in pairs]),
    )


def correspondences(
    opts: list[Options], labelling: tuple[int, ...], rig_points: np.ndarray, fixed_2d: np.ndarray, fixed_3d: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Under a labelling (one candidate index per detection): the found corners plus the fixed points,
    (n, 2) px and (n, 3) mm, and every rig corner's pixel (P, 2) in rig order, NaN where not found."""
    corners = np.full((len(rig_points), 2), np.nan)
    for o, c in zip(opts, labelling):
        corners[o.rig_index[c]] = o.corners_px[c]
    found = np.isfinite(corners[:, 0])
    return np.concatenate([corners[found], fixed_2d]), np.concatenate([rig_points[found], fixed_3d]), corners


def pnp_rms(points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Reprojection RMS (px) and pose of a PnP (SQPnP) under K; inf when OpenCV finds no pose."""
    try:
        rvec, tvec = solve_pnp_start(points_2d, points_3d, K)
    except InputError:
        return float("inf"), np.zeros(3), np.zeros(3)
    err = reprojection_errors(points_2d, points_3d, K, rvec, tvec)
    return float(np.sqrt(np.mean(err**2))), rvec, tvec


def complete(seed: tuple[int, ...], opts: list[Options], predicted_px: np.ndarray) -> tuple[int, ...]:
    """The seed's labelling extended to every detection: closest free candidates first, against the rig
    corners ``predicted_px`` (P, 2) px projected from the seed's pose."""
    costs = []
    for r in range(len(seed), len(opts)):
        o = opts[r]
        sq = ((o.corners_px - predicted_px[o.rig_index]) ** 2).sum(-1)
        costs += [(float(c), r, k) for k, c in enumerate(np.sqrt(np.nanmean(sq, axis=1)))]
    chosen = dict(enumerate(seed))
    used = {int(opts[r].board[c]) for r, c in chosen.items()}
    for _, r, k in sorted(costs):
        if r not in chosen and int(opts[r].board[k]) not in used:
            chosen[r] = k
            used.add(int(opts[r].board[k]))
    return tuple(chosen[r] for r in range(len(opts)))


def refit(
    points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray
) -> tuple[np.ndarray, least_squares.FitResult]:
    """Single-frame calibration (K and pose free, LM from the given start) of B labellings: points_2d
    (B, n, 2) px, points_3d (B, n, 3) mm. Returns the RMS (B,) px, inf where the points do not span 3D
    (K not observable), and the fit (K, pose)."""
    fit = least_squares.fit(
        points_2d,
        points_3d,
        np.ones(points_2d.shape[:2]),
        np.broadcast_to(K, (len(rvec), 3, 3)),
        rvec,
        tvec,
        fit_k=True,
    )
    err = reprojection_errors(points_2d, points_3d, fit.K, fit.rvec, fit.tvec)
    rms = np.sqrt(np.mean(err**2, axis=1))
    return np.where([spans_3d(p, RIG_VIEW_RATIO) for p in points_3d], rms, np.inf), fit


_NO_POINTS_2D, _NO_POINTS_3D = np.empty((0, 2)), np.empty((0, 3))  # no fixed correspondences


def identify(
    detections: list[Detection],
    rig: Rig,
    K_rough: np.ndarray,
    fixed_2d: np.ndarray = _NO_POINTS_2D,
    fixed_3d: np.ndarray = _NO_POINTS_3D,
) -> Identification:
    """Label every detection with its rig board (see the module doc). ``fixed_2d`` (m, 2) px and
    ``fixed_3d`` (m, 3) mm are known correspondences (labelled natural points) used in every fit.

    Raises IdentificationError when the labelling is ambiguous, CalibrationError when no labelling
    gives a single-frame K (the points do not span 3D).
    """
    order = sorted(range(len(detections)), key=lambda i: detections[i].board is None)
    opts = [options(detections[i], rig) for i in order]
    n_known = sum(detections[i].board is not None for i in order)
    n_seed = min(len(opts), max(n_known, 1 if len(fixed_3d) else 2))
    rig_points = rig.points()
    scored: dict[tuple[int, ...], tuple[float, np.ndarray, np.ndarray]] = {}
    for seed in itertools.product(*(range(len(o.board)) for o in opts[:n_seed])):
        if len({int(o.board[c]) for o, c in zip(opts, seed)}) < n_seed:
            continue
        rms, rvec, tvec = pnp_rms(*correspondences(opts[:n_seed], seed, rig_points, fixed_2d, fixed_3d)[:2], K_rough)
        if not np.isfinite(rms):
            continue
        labelling = complete(seed, opts, project(rig_points, K_rough, rvec, tvec))
        if labelling not in scored:
            scored[labelling] = pnp_rms(*correspondences(opts, labelling, rig_points, fixed_2d, fixed_3d)[:2], K_rough)
    best = sorted(scored, key=lambda lab: scored[lab][0])[:TOP_N]
    if not best:
        raise IdentificationError("no labelling of the boards found gives a camera pose")
    p2, p3, corners = zip(*(correspondences(opts, lab, rig_points, fixed_2d, fixed_3d) for lab in best))
    rms, fit = refit(
        np.stack(p2),
        np.stack(p3),
        K_rough,
        np.stack([scored[lab][1] for lab in best]),
        np.stack([scored[lab][2] for lab in best]),
    )
    rank = np.argsort(rms)
    win = int(rank[0])
    if not np.isfinite(rms[win]):
        raise CalibrationError("the points found lie (nearly) in one plane: K is not observable from this photo")
    runner_up = float(rms[rank[1]]) if len(rank) > 1 else float("inf")
    if runner_up < AMBIGUITY_RATIO * rms[win]:
        raise IdentificationError(
            f"ambiguous board identity: the best labelling leaves {rms[win]:.2f} px RMS, "
            f"the next {runner_up:.2f} px (needs {AMBIGUITY_RATIO:g}x apart)"
        )
    boards = dict(zip(order, (int(o.board[c]) for o, c in zip(opts, best[win]))))
    return Identification(
        corners_px=corners[win],
        boards=tuple(boards[i] for i in range(len(detections))),
        K=fit.K[win],
        rvec=fit.rvec[win],
        tvec=fit.tvec[win],
        rms_px=float(rms[win]),
        runner_up_rms_px=runner_up,
    )
