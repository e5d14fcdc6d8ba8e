"""The hot path's faster twins: one frame through OpenCV or plain floats, where numpy's batched
reference costs more per call. Each is held equal to its reference by a test
(tests/rectify/test_fast.py); the figures are µs per call for a 320-point frame, twin against
reference, measured on this project's 2-core VM pinned to one core (numpy 2.4, OpenCV 5.0).

| twin | reference | µs |
|---|---|---|
| ``frame_residuals`` | ``geometry.reprojection_residuals`` | 8 vs 21 |
| ``frame_mean_norm`` | ``geometry.mean_residual_norms`` | 3 vs 7 |
| ``all_inside`` | ``ImageBounds.inside(...).all()`` | 6 vs 26 |
| ``frame_within_bounds`` | ``ModelSpec.k_within_bounds`` | 0.9 vs 3.9 |

Elsewhere: ``geometry.covariance_invariants`` (OpenCV) twins ``covariance_invariants_batch``,
``geometry.rotation_matrices`` (OpenCV's Rodrigues for a few poses) twins ``rvec_to_matrix``,
and ``OnnxModel.frame_delta_k`` (an IO binding) twins ``OnnxModel.delta_k``.
"""

from __future__ import annotations

import cv2
import numpy as np

from dimenet.runtime.geometry import MAX_COORDINATE


def frame_residuals(
    points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray, R: np.ndarray, tvec: np.ndarray
) -> np.ndarray:
    """One frame's reprojection residuals pi(K (R X + t)) - x, (N, 2) px: points_2d (N, 2) px,
    points_3d (N, 3) mm float64, the pose {W}->{C} as R (3, 3) and tvec (3,) mm."""
    d = cv2.convertPointsFromHomogeneous(_homogeneous_pixels(points_3d, K, R, tvec)).reshape(-1, 2)
    d -= points_2d
    return d


def _homogeneous_pixels(points_3d: np.ndarray, K: np.ndarray, R: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(N, 1, 3) K (R X + t) of one frame's (N, 3) points through OpenCV: z (u, v, 1), z = Z_C."""
    Rt = np.empty((3, 4))
    Rt[:, :3], Rt[:, 3] = R, tvec
    return cv2.transform(points_3d.reshape(-1, 1, 3), K @ Rt)


def frame_mean_norm(residuals: np.ndarray) -> float:
    """Mean Euclidean norm (px) of one frame's (2, N) residuals (u row, v row)."""
    return cv2.sumElems(cv2.magnitude(residuals[0], residuals[1]))[0] / residuals.shape[1]


def frame_error_and_depth(points_2d, points_3d, K, rvec, tvec) -> tuple[float, float]:
    """One frame's mean Euclidean reprojection error (px) of its (N, 2) px / (N, 3) mm points under
    K (3, 3) at the pose rvec, tvec (3,), and the smallest depth Z_C of its points (mm, <= 0:
    a point behind the camera): OpenCV's transform gives z (u, v, 1), z = Z_C for a pinhole K."""
    h = _homogeneous_pixels(points_3d, K, cv2.Rodrigues(rvec)[0], tvec)
    d = cv2.convertPointsFromHomogeneous(h).reshape(-1, 2)
    d -= points_2d
    return frame_mean_norm(d.T), cv2.minMaxLoc(h[:, 0, 2])[0]


def all_inside(bounds, points_2d: np.ndarray, points_3d: np.ndarray) -> bool:
    """``bounds.inside(points_2d, points_3d).all()`` (an ``ImageBounds``): (N, 2), (N, 3) float64
    C-contiguous, or any leading dims. OpenCV's checks first (checkRange's range is
    [-MAX_COORDINATE, MAX_COORDINATE), as the reference's), numpy's when they say no."""
    if (
        cv2.checkRange(points_3d, True, -MAX_COORDINATE, MAX_COORDINATE)[0]
        and cv2.countNonZero(cv2.inRange(points_2d.reshape(-1, 1, 2), *bounds.cv_bounds)) == points_2d.size // 2
    ):
        return True
    return bool(bounds.inside(points_2d, points_3d).all())


def frame_within_bounds(k: list, K_bounds: list) -> bool:
    """The K-bounds rule on one frame's k = [fx, fy, cx, cy] (px, floats) against K_bounds as 4
    [low, high] lists: plain float comparisons, where a NaN fails too."""
    return all(low <= v <= high for v, (low, high) in zip(k, K_bounds))
