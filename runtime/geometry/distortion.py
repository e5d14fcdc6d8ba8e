"""Lens distortion in OpenCV's model, the one home of distorting and undistorting pixels.

A lens's distortion is fixed while OIS moves K, so it is stated about the camera's fixed K_c:
a pinhole pixel x (px, under K_c, OpenCV's convention) is what the lens would have imaged
without distortion, and ``distort_points`` maps it to the pixel the real image holds;
``undistort_points`` is its inverse. ``dist_coeffs`` are OpenCV's 4, 5, 8, 12 or 14
coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tau_x, tau_y]]]]), scale-free.
"""

from __future__ import annotations

import cv2
import numpy as np

from dimenet.runtime.geometry.projection import mean_over, project

# Undistortion is iterative: to this step (in normalised image coordinates, i.e. 1e-12 f px)
# or this many iterations. OpenCV's default (5 iterations) leaves up to 0.1 px at an image
# corner under k1 = -0.3; 20 reach 1e-9 px there.
UNDISTORT_ITERATIONS = 20
UNDISTORT_EPSILON = 1e-12
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, UNDISTORT_ITERATIONS, UNDISTORT_EPSILON)
# OpenCV 4 takes the criteria in undistortPointsIter; OpenCV 5 in undistortPoints itself.
_undistort = getattr(cv2, "undistortPointsIter", None) or cv2.undistortPoints


def _rays(points_2d: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) pinhole px under K (3, 3) -> (N, 3) their rays (a, b, 1) in K's normalised coordinates."""
    rays = np.ones((len(points_2d), 3))
    rays[:, 0] = (points_2d[:, 0] - K[0, 2]) / K[0, 0]
    rays[:, 1] = (points_2d[:, 1] - K[1, 2]) / K[1, 1]
    return rays


def undistort_points(points_2d: np.ndarray, K: np.ndarray, dist_coeffs: np.ndarray) -> np.ndarray:
    """(..., 2) distorted px -> (..., 2) pinhole px under the same K (3, 3) px; NaN stays NaN."""
    points_2d = np.asarray(points_2d, dtype=np.float64)
    flat = points_2d.reshape(-1, 1, 2)
    finite = np.all(np.isfinite(flat[:, 0]), axis=1)
    out = np.full_like(flat, np.nan)
    if finite.any():
        out[finite] = _undistort(
            np.ascontiguousarray(flat[finite]), K, np.asarray(dist_coeffs, np.float64), R=None, P=K, criteria=_CRITERIA
        )
    return out.reshape(points_2d.shape)


def distort_points(points_2d: np.ndarray, K: np.ndarray, dist_coeffs: np.ndarray) -> np.ndarray:
    """(..., 2) pinhole px under K (3, 3) px -> (..., 2) distorted px (the lens's image); NaN stays NaN."""
    points_2d = np.asarray(points_2d, dtype=np.float64)
    flat = points_2d.reshape(-1, 2)
    finite = np.all(np.isfinite(flat), axis=1)
    out = np.full_like(flat, np.nan)
    if finite.any():
        projected, _ = cv2.projectPoints(
            _rays(flat[finite], K), np.zeros(3), np.zeros(3), K, np.asarray(dist_coeffs, np.float64)
        )
        out[finite] = projected.reshape(-1, 2)
    return out.reshape(points_2d.shape)


def distort_points_with_jacobians(points_2d: np.ndarray, K: np.ndarray, dist_coeffs: np.ndarray) -> tuple:
    """(N, 2) finite pinhole px under K (3, 3) px -> the distorted px (N, 2), their derivatives
    (N, 2, 2) by the pinhole px and (N, 2, n) by the n ``dist_coeffs`` (OpenCV's analytic ones)."""
    coeffs = np.asarray(dist_coeffs, np.float64)
    projected, J = cv2.projectPoints(_rays(points_2d, K), np.zeros(3), np.zeros(3), K, coeffs)
    J = J.reshape(len(points_2d), 2, -1)
    # Columns: rvec (3), tvec (3), f (2), c (2), the coefficients. A ray (a, b, 1) moved by tvec
    # (dx, dy, 0) is the ray (a + dx, b + dy, 1): d/d tvec_x,y are d/da, d/db, and a = (u - cx) / fx.
    by_pixel = J[..., 3:5] / np.array([K[0, 0], K[1, 1]])
    return projected.reshape(-1, 2), by_pixel, J[..., 10 : 10 + len(coeffs)]


def mean_distorted_error(points_2d, points_3d, valid, K, rvec, tvec, K_lens, dist_coeffs) -> np.ndarray:
    """Mean Euclidean reprojection error (px) of B frames in the distorted image: points_2d
    (B, N, 2) px as the image holds them, points_3d (B, N, 3) mm {W}, valid (B, N) bool or None
    (all), K (B, 3, 3) or (3, 3) px the frames' pinhole K, rvec/tvec (B, 3) {W}->{C}; the lens
    (K_lens (3, 3) px, dist_coeffs) distorts the pinhole projection. -> (B,) px."""
    pinhole = project(np.asarray(points_3d, np.float64), np.asarray(K, np.float64), rvec, tvec)
    distorted = distort_points(pinhole, K_lens, dist_coeffs)
    norms = np.linalg.norm(distorted - points_2d, axis=-1)
    return mean_over(norms, valid)
