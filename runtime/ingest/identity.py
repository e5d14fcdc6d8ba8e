"""Telling a photo's boards apart: which rig board, turned which way, each detection is.

ChArUco detections come identified by their markers. Plain boards of one pattern are
identical, so a plain detection may be any of them, turned by any symmetry of its grid (0° or
180°; 90° and 270° too for a square grid); and a detector asked for one pattern may return a
window of a larger board, or of a grid grown at a fold (``refine.grow``), so the candidates are
every plain board whose pattern fits in the detection's grid, at every quarter turn and offset
where it fits (``candidates``). A *labelling* gives every detection one candidate, each board at
most once.

1. Seeds: every labelling of the first detections (identified ones first, then those with the
   fewest candidates; two detections, or one when labelled natural points are known too). A PnP
   (SQPnP) with a rough K on the seed's corners fixes the camera (two boards lie on different
   planes); every other detection takes the free candidate whose projected corners lie closest
   (RMS px).
2. Every distinct completed labelling is scored by the reprojection RMS (px) of a PnP with the
   rough K on all the photo's points; the TOP_N best (or fewer: ``refits``) are refitted with a free K (the
   single-frame calibration: LM over K and pose, ``least_squares.fit``, from the rough K and
   the PnP pose): ranked by a short fit first, the best two and any close to the second in full.
3. The best refit wins (``label``); ``identify`` also asks that the next one leaves at least
   AMBIGUITY_RATIO times its RMS, otherwise the photo is ambiguous (e.g. a rig that looks nearly
   the same turned round, or two boards meeting at a fold whose one-square shift along it is a
   translation of the rig).

Pixels: x right, y down; 3D in mm in the rig frame {W}.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from dimenet.runtime.errors import CalibrationError, IdentificationError, InputError
from dimenet.runtime.formats.rig import Rig
from dimenet.runtime.geometry import (
    RIG_VIEW_RATIO,
    k_matrix,
    least_squares,
    project,
    reprojection_errors,
    solve_pnp_start,
    spans_3d,
)
from dimenet.runtime.ingest.detection import Detection
from dimenet.runtime.ingest.grid import placements

ROUGH_FOCAL = 0.75  # rough focal length / the image's longer side: a phone's main camera (≈ 26 mm equivalent)
TOP_N = 4  # labellings refitted with a free K
# More than two refits are ranked by a fit of RANK_ITERATIONS LM iterations first; only the best two, and any
# within RANK_MARGIN of the second's RMS, are fitted in full (the runner-up's RMS is reported). More iterations
# only lower an RMS; from 10 to the full fit's 50 they lowered none by more than 1.19x (the rankings of 64 photos:
# 60 rendered of the paper rig, 3 cameras, one through a lens; the 4 real ortho-rig photos).
RANK_ITERATIONS = 10
RANK_MARGIN = 1.5
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
    # The cameras (K, rvec, tvec) of the other labellings refitted within AMBIGUITY_RATIO of the winner's
    # RMS: where each would put the boards not found (``pipeline.find_and_label`` looks there too).
    close: tuple = ()


def rough_k(image_size: tuple[int, int]) -> np.ndarray:
    """(3, 3) px a rough K for a (width, height) image: ROUGH_FOCAL x the longer side, centred."""
    w, h = image_size
    f = ROUGH_FOCAL * max(w, h)
    return k_matrix([f, f, (w - 1) / 2.0, (h - 1) / 2.0])


@dataclass(frozen=True)
class Candidate:
    """One (board, turn, offset) a detection may be: ``corners_px`` (n, 2) px the detection's corners in the
    board's corner order, ``rig_index`` (n,) the rig corner (row of ``Rig.points()``) of each."""

    board: int  # rig board index
    corners_px: np.ndarray
    rig_index: np.ndarray


def candidates(detection: Detection, rig: Rig) -> list[Candidate]:
    """A detection's candidates: its own board when identified, else every plain board placed in its grid
    under every quarter turn and offset where it fits (``grid.placements``: 0° and 180° of its own pattern,
    90° and 270° too for a square one, and more where the grid was grown at a fold)."""
    start = np.r_[0, np.cumsum([b.n_points for b in rig.boards])]
    if detection.board is not None:
        n = len(detection.corners_px)
        return [Candidate(detection.board, detection.corners_px, start[detection.board] + np.arange(n))]
    return [
        Candidate(b, detection.corners_px[perm], start[b] + np.arange(len(perm)))
        for b, board in enumerate(rig.boards)
        if board.aruco is None
        for perm in placements(detection.grid_shape, board.inner_corners)
    ]


def correspondences(
    opts: list[list[Candidate]],
    labelling: tuple[int, ...],
    rig_points: np.ndarray,
    fixed_2d: np.ndarray,
    fixed_3d: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Under a labelling (one candidate index per detection): the found corners plus the fixed points,
    (n, 2) px and (n, 3) mm, and every rig corner's pixel (P, 2) in rig order, NaN where not found."""
    corners = np.full((len(rig_points), 2), np.nan)
    for o, c in zip(opts, labelling):
        corners[o[c].rig_index] = o[c].corners_px
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


def stacked(options: list[Candidate]) -> tuple[np.ndarray, np.ndarray]:
    """One detection's candidates stacked: their corners (K, n, 2) px and rig corners (K, n), padded to the
    most corners with NaN corners (of rig corner 0)."""
    n = max(len(c.rig_index) for c in options)
    corners = np.full((len(options), n, 2), np.nan)
    rig_index = np.zeros((len(options), n), dtype=int)
    for k, c in enumerate(options):
        corners[k, : len(c.rig_index)] = c.corners_px
        rig_index[k, : len(c.rig_index)] = c.rig_index
    return corners, rig_index


def complete(
    seeds: list[tuple[int, ...]],
    opts: list[list[Candidate]],
    rig_points: np.ndarray,
    fixed_2d: np.ndarray,
    fixed_3d: np.ndarray,
    K: np.ndarray,
) -> list[tuple[int, ...]]:
    """The seeds (labellings of the first detections) extended to every detection: a PnP (SQPnP) under K on
    a seed's points fixes its camera (a seed without a pose is dropped), then each other detection takes the
    free candidate whose corners lie closest (RMS px) to the rig corners projected, closest first."""
    poses = {}
    for seed in seeds:
        try:
            poses[seed] = solve_pnp_start(*correspondences(opts, seed, rig_points, fixed_2d, fixed_3d)[:2], K)
        except InputError:
            continue
    if not poses:
        return []
    rvec, tvec = (np.array(a) for a in zip(*poses.values()))
    predicted_px = project(rig_points, K, rvec, tvec)  # (S, P, 2)
    n_seed = len(seeds[0])
    costs = []
    for o in opts[n_seed:]:
        corners, rig_index = stacked(o)
        costs.append(np.sqrt(np.nanmean(np.sum((corners - predicted_px[:, rig_index]) ** 2, axis=-1), axis=-1)))
    pairs = [(r, k) for r in range(n_seed, len(opts)) for k in range(len(opts[r]))]
    labellings = []
    for seed, cost in zip(poses, np.concatenate(costs, axis=1)):
        chosen = dict(enumerate(seed))
        used = {opts[r][c].board for r, c in chosen.items()}
        for i in np.argsort(cost, kind="stable"):
            r, k = pairs[i]
            if r not in chosen and opts[r][k].board not in used:
                chosen[r] = k
                used.add(opts[r][k].board)
        labellings.append(tuple(chosen[r] for r in range(len(opts))))
    return labellings


def refit(
    points_2d: list[np.ndarray],
    points_3d: list[np.ndarray],
    K: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    **lm_options: float,
) -> tuple[np.ndarray, least_squares.FitResult]:
    """Single-frame calibration (K and pose free, LM from the given start) of B labellings: points_2d
    (n_b, 2) px, points_3d (n_b, 3) mm each; ``lm_options``: ``least_squares.fit``'s (max_iterations,
    tolerance). Returns the RMS (B,) px, inf where the points do not span 3D (K not observable), and the
    fit (K, pose)."""
    n = max(len(p) for p in points_2d)
    weights = np.array([np.r_[np.ones(len(p)), np.zeros(n - len(p))] for p in points_2d])
    p2 = np.stack([np.vstack([p, np.zeros((n - len(p), 2))]) for p in points_2d])
    p3 = np.stack([np.vstack([p, np.zeros((n - len(p), 3))]) for p in points_3d])
    fit = least_squares.fit(
        p2, p3, weights, np.broadcast_to(K, (len(rvec), 3, 3)), rvec, tvec, fit_k=True, **lm_options
    )
    err = reprojection_errors(p2, p3, fit.K, fit.rvec, fit.tvec)
    rms = np.sqrt(np.sum(weights * err**2, axis=1) / weights.sum(1))
    return np.where([spans_3d(p, RIG_VIEW_RATIO) for p in points_3d], rms, np.inf), fit


_NO_POINTS_2D, _NO_POINTS_3D = np.empty((0, 2)), np.empty((0, 3))  # no fixed correspondences


def label(
    detections: list[Detection],
    rig: Rig,
    K_rough: np.ndarray,
    fixed_2d: np.ndarray = _NO_POINTS_2D,
    fixed_3d: np.ndarray = _NO_POINTS_3D,
    refits: int = TOP_N,
) -> Identification:
    """The best labelling of the detections with rig boards (see the module doc) and its single-frame fit,
    with the runner-up's RMS, however close (inf with ``refits`` = 1: only the best PnP labelling refitted).
    ``fixed_2d`` (m, 2) px and ``fixed_3d`` (m, 3) mm are known correspondences (labelled natural points)
    used in every fit.

    Raises IdentificationError when no labelling gives a camera pose, CalibrationError when none gives a
    single-frame K (the points do not span 3D).
    """
    all_opts = [candidates(d, rig) for d in detections]
    order = sorted(range(len(detections)), key=lambda i: (detections[i].board is None, len(all_opts[i])))
    opts = [all_opts[i] for i in order]
    n_known = sum(detections[i].board is not None for i in order)
    n_seed = min(len(opts), max(n_known, 1 if len(fixed_3d) else 2))
    rig_points = rig.points()
    seeds = [
        seed
        for seed in itertools.product(*(range(len(o)) for o in opts[:n_seed]))
        if len({o[c].board for o, c in zip(opts, seed)}) == n_seed
    ]
    # A seed of every detection is a labelling already: its one PnP scores it.
    labellings = complete(seeds, opts, rig_points, fixed_2d, fixed_3d, K_rough) if n_seed < len(opts) else seeds
    scored: dict[tuple[int, ...], tuple[float, np.ndarray, np.ndarray]] = {}
    for labelling in labellings:  # distinct: each keeps its seed
        score = pnp_rms(*correspondences(opts, labelling, rig_points, fixed_2d, fixed_3d)[:2], K_rough)
        if np.isfinite(score[0]):
            scored[labelling] = score
    best = sorted(scored, key=lambda lab: scored[lab][0])[:refits]
    if not best:
        raise IdentificationError("no labelling of the boards found gives a camera pose")
    p2, p3, corners = (
        list(a) for a in zip(*(correspondences(opts, lab, rig_points, fixed_2d, fixed_3d) for lab in best))
    )
    rvec, tvec = np.stack([scored[lab][1] for lab in best]), np.stack([scored[lab][2] for lab in best])
    full = np.arange(len(best))  # the labellings fitted in full
    if len(best) > 2:  # ranked by a short fit first: only the best two and any close to the second need the full one
        short, _ = refit(p2, p3, K_rough, rvec, tvec, max_iterations=RANK_ITERATIONS)
        ranked = np.argsort(short)
        full = np.sort(ranked[: max(2, int(np.sum(short <= RANK_MARGIN * short[ranked[1]])))])
    rms, fit = refit([p2[i] for i in full], [p3[i] for i in full], K_rough, rvec[full], tvec[full])
    rank = np.argsort(rms)
    win = int(rank[0])
    if not np.isfinite(rms[win]):
        raise CalibrationError("the points found lie (nearly) in one plane: K is not observable from this photo")
    boards = dict(zip(order, (o[c].board for o, c in zip(opts, best[full[win]]))))
    return Identification(
        corners_px=corners[full[win]],
        boards=tuple(boards[i] for i in range(len(detections))),
        K=fit.K[win],
        rvec=fit.rvec[win],
        tvec=fit.tvec[win],
        rms_px=float(rms[win]),
        runner_up_rms_px=float(rms[rank[1]]) if len(rank) > 1 else float("inf"),
        close=tuple((fit.K[i], fit.rvec[i], fit.tvec[i]) for i in rank[1:] if rms[i] < AMBIGUITY_RATIO * rms[win]),
    )


def ambiguous(found: Identification) -> bool:
    """Whether the runner-up labelling leaves less than AMBIGUITY_RATIO times the winner's RMS."""
    return found.runner_up_rms_px < AMBIGUITY_RATIO * found.rms_px


def check_unambiguous(found: Identification) -> None:
    """IdentificationError unless the runner-up labelling leaves at least AMBIGUITY_RATIO times the winner's RMS."""
    if ambiguous(found):
        raise IdentificationError(
            f"ambiguous board identity: the best labelling leaves {found.rms_px:.2f} px RMS, "
            f"the next {found.runner_up_rms_px:.2f} px (needs {AMBIGUITY_RATIO:g}x apart)"
        )


def identify(detections: list[Detection], rig: Rig, K_rough: np.ndarray) -> Identification:
    """``label`` (no known correspondences), then ``check_unambiguous``: raises IdentificationError when the
    labelling is ambiguous or gives no pose, CalibrationError when no labelling gives a single-frame K."""
    found = label(detections, rig, K_rough)
    check_unambiguous(found)
    return found


def upright(options: list[Candidate], rig: Rig) -> Candidate:
    """Of one board's candidates, the one turned upright in the image: its grid x (the mean of each row's last
    minus first corner, px) closest to the image's +x, then its first corner highest."""

    def key(c: Candidate) -> tuple[float, float]:
        g = c.corners_px.reshape(-1, rig.boards[c.board].inner_corners[0], 2)
        ex = np.nanmean(g[:, -1] - g[:, 0], axis=0)
        return -float(ex[0] / max(float(np.linalg.norm(ex)), 1e-12)), float(c.corners_px[0, 1])

    return min(options, key=key)


def label_planar(detection: Detection, rig: Rig) -> tuple[int, np.ndarray]:
    """The rig board of a photo's one detection, and every rig corner's pixel (P, 2) in rig order (NaN where
    not found): a planar frame, whose K one view cannot tell. The detection's own board when identified; else
    the one plain board it may be, turned upright (``upright``: one plane alone cannot tell a turn, and every
    turn is a valid pose). Raises IdentificationError when it may be more than one board, or sit at more than
    one place in its grid (grown at a fold)."""
    options = candidates(detection, rig)
    boards = sorted({c.board for c in options})
    if len(boards) > 1:
        names = ", ".join(repr(rig.boards[b].name) for b in boards)
        raise IdentificationError(f"one board alone cannot be told apart: it may be any of {names}")
    if detection.board is None and detection.grid_shape != detection.pattern:
        raise IdentificationError(
            f"the board's grid of {detection.grid_shape[0]}x{detection.grid_shape[1]} corners runs past its "
            f"{detection.pattern[0]}x{detection.pattern[1]} pattern: one board alone cannot tell where it sits"
        )
    chosen = options[0] if detection.board is not None else upright(options, rig)
    corners = np.full((rig.n_points, 2), np.nan)
    corners[chosen.rig_index] = chosen.corners_px
    return chosen.board, corners
