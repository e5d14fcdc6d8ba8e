"""The ``self`` baseline: each frame's K from its own inference points alone (joint K + pose).

What a user could do without any model: per-frame calibration (DLT start, then LM over
(fx, fy, cx, cy) and the pose; ``geometry.least_squares.calibrate``) on the points K is inferred from.
Where K is not observable from the frame, it says so and falls back to K_c instead of
returning garbage: fewer than 6 inference points, (nearly) coplanar 3D points (one planar
view cannot fix K), a fit that fails, or a K that is not a camera of this image (focal
lengths not positive, principal point outside the image).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import MIN_POINTS, calibrate, k_params


@dataclass(frozen=True)
class SelfCalibration:
    """K (F, 3, 3) px per frame (K_c where it fell back); fallback: per frame None or why."""

    K: np.ndarray
    fallback: tuple


def _implausible(K: np.ndarray, image_size) -> str | None:
    fx, fy, cx, cy = k_params(K)
    width, height = image_size
    if not np.all(np.isfinite([fx, fy, cx, cy])):
        return "the fit diverged (K not finite)"
    if fx <= 0 or fy <= 0 or not (0 <= cx <= width and 0 <= cy <= height):
        return f"the fit gives no camera of this image (fx={fx:.1f}, fy={fy:.1f}, cx={cx:.1f}, cy={cy:.1f} px)"
    return None


def self_calibrate(frames: Dataset, K_c: np.ndarray) -> SelfCalibration:
    """Per-frame joint (K, pose) on each frame's inference points; K_c where that is ill-posed."""
    F = frames.n_frames
    K = np.broadcast_to(np.asarray(K_c, dtype=np.float64), (F, 3, 3)).copy()
    reasons: list = [None] * F
    counts = frames.infer_mask.sum(1)
    enough = counts >= MIN_POINTS
    for f in np.flatnonzero(~enough):
        reasons[f] = f"{int(counts[f])} inference points: K from one frame needs >= {MIN_POINTS}"
    idx = np.flatnonzero(enough)
    res = calibrate(frames.points_2d[idx], frames.points_3d[idx], frames.infer_mask[idx], partial=True)
    for f, K_f, reason in zip(idx, res.K, res.reasons):
        reasons[f] = f"ill-posed: {reason}" if reason is not None else _implausible(K_f, frames.image_size)
        if reasons[f] is None:
            K[f] = K_f
    return SelfCalibration(K=K, fallback=tuple(reasons))
