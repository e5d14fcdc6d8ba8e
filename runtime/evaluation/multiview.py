"""One camera from many views: the joint fit of K_c and one lens distortion over all of a
dataset's frames (Zhang's multi-view calibration, ``cv2.calibrateCamera``).

Where one frame cannot give K (its points lie in one plane: a single printed board), several
views of it can; and a lens's distortion is one for all frames (the lens is fixed, OIS moves
K), so it is fitted jointly. Models (``DISTORTION_MODELS``): ``none`` (pinhole), ``opencv4``
(k1, k2, p1, p2), ``opencv5`` (+ k3), ``opencv8`` (the rational model, k1..k6, p1, p2).

Planar views start the fit (homographies, whatever plane the board lies in: each is turned
into its own plane's coordinates first); without any, the caller's K guess does. The final
fit runs on every view's own 3D points from that start.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime.errors import CalibrationError
from dimenet.runtime.geometry import MIN_POINTS, spans_3d

_FIXED = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
DISTORTION_MODELS = {
    "none": (_FIXED, 0),
    "opencv4": (cv2.CALIB_FIX_K3, 4),
    "opencv5": (0, 5),
    "opencv8": (cv2.CALIB_RATIONAL_MODEL, 8),
}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class JointFit:
    """K (3, 3) px; dist_coeffs (n,) of the model (None for ``none``); rms_px the fit's RMS
    reprojection error over all points; views: how many frames it used (planar ones of them)."""

    K: np.ndarray
    dist_coeffs: Optional[np.ndarray]
    rms_px: float
    views: int
    planar_views: int


def _plane_coordinates(points_3d: np.ndarray) -> np.ndarray:
    """(N, 3) nearly coplanar points -> (N, 3) the same in their plane's own frame (Z = 0)."""
    centred = points_3d - points_3d.mean(0)
    basis = np.linalg.svd(centred, full_matrices=False)[2]
    inplane = centred @ basis[:2].T
    return np.c_[inplane, np.zeros(len(points_3d))]


def distortion_coefficients(model: str) -> int:
    """How many of OpenCV's coefficients ``model`` fits (0 for ``none``); CalibrationError if unknown."""
    if model not in DISTORTION_MODELS:
        raise CalibrationError(f"distortion: unknown model {model!r} (known: {', '.join(DISTORTION_MODELS)})")
    return DISTORTION_MODELS[model][1]


def joint_fit(frames: list, image_size, model: str = "none", K_guess: Optional[np.ndarray] = None) -> JointFit:
    """K_c and one distortion of ``model`` from ``frames``: (points_2d (N, 2) px, points_3d (N, 3)
    mm) pairs, one per view, each with >= MIN_POINTS points; image_size (width, height) px.
    K_guess (3, 3) px starts the fit when no view is planar. CalibrationError when nothing can."""
    n_coeffs = distortion_coefficients(model)
    flags = DISTORTION_MODELS[model][0]
    views = [(np.asarray(x, np.float64), np.asarray(X, np.float64)) for x, X in frames if len(x) >= MIN_POINTS]
    if not views:
        raise CalibrationError(f"a joint fit needs views of >= {MIN_POINTS} points, got none")
    planar = [(x, X) for x, X in views if not spans_3d(X)]
    size = tuple(int(v) for v in image_size)
    dist = np.zeros(max(n_coeffs, 5))
    try:
        if planar:
            objects = [_plane_coordinates(X).astype(np.float32) for _, X in planar]
            images = [x.astype(np.float32).reshape(-1, 1, 2) for x, _ in planar]
            _, K, dist, _, _ = cv2.calibrateCamera(objects, images, size, None, None, flags=flags, criteria=_CRITERIA)
        elif K_guess is not None:
            K = np.array(K_guess, np.float64)
        else:
            raise CalibrationError("a joint fit of non-planar views needs a K to start from")
        objects = [X.astype(np.float32) for _, X in views]
        images = [x.astype(np.float32).reshape(-1, 1, 2) for x, _ in views]
        rms, K, dist, _, _ = cv2.calibrateCamera(
            objects, images, size, K, dist, flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=_CRITERIA
        )
    except cv2.error as exc:
        raise CalibrationError(f"the joint fit failed: {str(exc).strip().splitlines()[-1]}") from None
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and np.isfinite(rms) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(f"the joint fit diverged (K {np.round(K, 1).tolist()})")
    coeffs = None if n_coeffs == 0 else np.asarray(dist, np.float64).ravel()[:n_coeffs].copy()
    return JointFit(
        K=np.asarray(K, np.float64), dist_coeffs=coeffs, rms_px=float(rms), views=len(views), planar_views=len(planar)
    )
