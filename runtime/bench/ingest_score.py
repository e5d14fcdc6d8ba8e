"""How an ingested dataset measures up against the renderer's truth (``formats.render_truth``).

Scores: boards found among those the renderer shows whole, boards put on the wrong rig board or
turned the wrong way, corner error (px) against the true projections, and the per-frame K* of
the ingested points against the renderer's K.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.calibration import oracle_fit
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.render_truth import Truth
from dimenet.runtime.geometry import k_params, undistort_points

IDENTITY_TOLERANCE_PX = 5.0  # a found board further than this (RMS) from its true corners has the wrong identity


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
