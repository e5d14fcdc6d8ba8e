"""The renderer's truth (``truth.npz``, see models_spec/ingest.md) and how an ingested dataset measures up.

Scores: boards found among those the renderer shows whole, boards put on the wrong rig board or
turned the wrong way, corner error (px) against the true projections, and the per-frame K* of
the ingested points against the renderer's K.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.calibration import LENS_KEYS, oracle_fit
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.npz import read_npz
from dimenet.runtime.geometry import k_params
from dimenet.runtime.geometry.distortion import undistort_points

IDENTITY_TOLERANCE_PX = 5.0  # a found board further than this (RMS) from its true corners has the wrong identity


@dataclass(frozen=True)
class Truth:
    """Per photo: file name (N,), K (N, 3, 3) px, pose {W}->{C} (N, 3) rad / mm, every rig corner's true
    pixel (N, P, 2) and whether its board is shown whole (N, P); the rig's board of each corner (P,);
    the lens the photos were taken through (dist_coeffs (n,) about dist_K (3, 3) px), or None."""

    frame_id: np.ndarray
    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    corners_px: np.ndarray
    seen: np.ndarray
    board_of_point: np.ndarray
    upside_down: np.ndarray  # (N,) bool
    covered_board: np.ndarray  # (N,) int, -1 for none
    dist_coeffs: Optional[np.ndarray] = None
    dist_K: Optional[np.ndarray] = None


def _truth_array(arrays: dict, key: str, kinds: str, shape: tuple, named: str) -> np.ndarray:
    """``arrays[key]`` if its dtype kind is one of ``kinds`` and its shape is ``shape`` (``named``: as the spec
    writes it); floats as float64."""
    a = arrays[key]
    if a.dtype.kind not in kinds or a.shape != shape:
        kind = {"f": "a float", "b": "a bool", "iu": "an integer", "U": "a string"}[kinds]
        raise DatasetError(f"{key}: must be {kind} array of shape {named}, got {a.dtype} {a.shape}")
    return a.astype(np.float64, copy=False) if kinds == "f" else a


def read_truth(path: str | Path) -> Truth:
    """Read a renderer's truth.npz (never pickle-loads). Raises DatasetError naming the file: also for a
    corrupt, truncated or oversized archive (refused before decoding) and for arrays of the wrong shape."""
    arrays = read_npz(path, DatasetError, "render truth file")
    missing = [k for k in Truth.__dataclass_fields__ if k not in arrays and k not in LENS_KEYS]
    if missing:
        raise DatasetError(f"{path}: not a render truth file (missing {missing[0]!r})")
    try:
        frame_id = arrays["frame_id"]
        N = frame_id.shape[0] if frame_id.ndim == 1 else -1
        P = arrays["board_of_point"].shape[0] if arrays["board_of_point"].ndim == 1 else -1
        lens = {}
        if any(k in arrays for k in LENS_KEYS):
            if not all(k in arrays for k in LENS_KEYS):
                raise DatasetError(f"{LENS_KEYS[0]} and {LENS_KEYS[1]}: give both or neither")
            n = arrays["dist_coeffs"].shape[0] if arrays["dist_coeffs"].ndim == 1 else -1
            lens = {
                "dist_coeffs": _truth_array(arrays, "dist_coeffs", "f", (n,), "(n,)"),
                "dist_K": _truth_array(arrays, "dist_K", "f", (3, 3), "(3, 3)"),
            }
        return Truth(
            frame_id=_truth_array(arrays, "frame_id", "U", (N,), "(N,)"),
            K=_truth_array(arrays, "K", "f", (N, 3, 3), "(N, 3, 3)"),
            rvec=_truth_array(arrays, "rvec", "f", (N, 3), "(N, 3)"),
            tvec=_truth_array(arrays, "tvec", "f", (N, 3), "(N, 3)"),
            corners_px=_truth_array(arrays, "corners_px", "f", (N, P, 2), "(N, P, 2)"),
            seen=_truth_array(arrays, "seen", "b", (N, P), "(N, P)"),
            board_of_point=_truth_array(arrays, "board_of_point", "iu", (P,), "(P,)"),
            upside_down=_truth_array(arrays, "upside_down", "b", (N,), "(N,)"),
            covered_board=_truth_array(arrays, "covered_board", "iu", (N,), "(N,)"),
            **lens,
        )
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None


@dataclass(frozen=True)
class IngestScore:
    """An ingested dataset against the truth (rig corners only)."""

    photos: int
    frames: int
    boards_shown: int  # boards the renderer shows whole, over all photos
    boards_found: int  # of those, found in an ingested frame
    extra_boards: int  # boards found that the truth does not count as whole (e.g. the occluder touches their margin)
    identity_errors: int  # boards found whose corners are not their rig board's (or turned the wrong way)
    corner_rms_px: float  # RMS corner error of the correctly identified boards
    corner_max_px: float
    k_error_px: float  # mean |K* - K_true| over fx, fy, cx, cy and frames (K* fitted on each frame alone)

    @property
    def detection_rate(self) -> float:
        return self.boards_found / self.boards_shown if self.boards_shown else float("nan")


def score(dataset: Dataset, truth: Truth) -> IngestScore:
    """Score ``dataset`` (from ``dimenet ingest`` of the rendered photos) against their ``truth``."""
    row = {str(name): k for k, name in enumerate(truth.frame_id)}
    missing = [str(f) for f in dataset.frame_id if str(f) not in row]
    if missing:
        raise DatasetError(f"frame_id: {missing[0]} is not a rendered photo")
    rows = np.array([row[str(f)] for f in dataset.frame_id])
    P = len(truth.board_of_point)
    boards = np.unique(truth.board_of_point)
    shown = np.stack([truth.seen[:, truth.board_of_point == b].all(1) for b in boards], 1)  # (N, B)
    found = np.zeros_like(shown)
    errors, identity_errors = [], 0
    for f, t in enumerate(rows):
        for b in boards:
            on = dataset.valid[f, :P] & (truth.board_of_point == b)
            if not on.any():
                continue
            found[t, b] = True
            err = np.linalg.norm(dataset.points_2d[f, :P][on] - truth.corners_px[t][on], axis=1)
            if np.sqrt(np.mean(err**2)) > IDENTITY_TOLERANCE_PX:
                identity_errors += 1
            else:
                errors.append(err)
    err = np.concatenate(errors) if errors else np.array([np.nan])
    points = dataset.points_2d
    if truth.dist_coeffs is not None:  # K* of the pinhole camera: the points undistorted by the true lens
        points = undistort_points(points, truth.dist_K, truth.dist_coeffs)
    K_star = oracle_fit(points, dataset.points_3d, dataset.valid)[0]
    return IngestScore(
        photos=len(truth.frame_id),
        frames=dataset.n_frames,
        boards_shown=int(shown.sum()),
        boards_found=int((found & shown).sum()),
        extra_boards=int((found & ~shown).sum()),
        identity_errors=identity_errors,
        corner_rms_px=float(np.sqrt(np.mean(err**2))),
        corner_max_px=float(err.max()),
        k_error_px=float(np.abs(k_params(K_star) - k_params(truth.K[rows])).mean()),
    )
