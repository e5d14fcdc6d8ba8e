"""The pinhole camera: K as (fx, fy, cx, cy), projection {W} -> {C} -> pixels, reprojection residuals and errors."""

from __future__ import annotations

import cv2
import numpy as np

from dimenet.runtime.geometry.rotation import rotated, rotation_matrices, rvec_to_matrix

# Smallest depth (mm) a point may have in front of the camera and still be projected.
MIN_DEPTH_MM = 1e-6


def k_params(K: np.ndarray) -> np.ndarray:
    """(..., 3, 3) intrinsic matrices -> (..., 4) as (fx, fy, cx, cy) in pixels."""
    return np.asarray(K, dtype=np.float64)[..., (0, 1, 0, 1), (0, 1, 2, 2)]


def k_matrix(params: np.ndarray) -> np.ndarray:
    """(..., 4) (fx, fy, cx, cy) in pixels -> (..., 3, 3) zero-skew intrinsic matrices."""
    params = np.asarray(params, dtype=np.float64)
    if params.shape == (4,):  # one K (the rectifier's hot path): 1.5 against 5 us
        fx, fy, cx, cy = params.tolist()
        return np.array(((fx, 0.0, cx), (0.0, fy, cy), (0.0, 0.0, 1.0)))
    K = np.zeros(params.shape[:-1] + (3, 3))
    K[..., 0, 0] = params[..., 0]
    K[..., 1, 1] = params[..., 1]
    K[..., 0, 2] = params[..., 2]
    K[..., 1, 2] = params[..., 3]
    K[..., 2, 2] = 1.0
    return K


def rescaled_px(px: np.ndarray, scale: float) -> np.ndarray:
    """Pixel coordinates (points (..., 2), principal points, or one coordinate) -> the same places in
    the image resized ``scale`` times per side: scale * (x + 0.5) - 0.5, a scale about the top-left
    pixel's corner (pixel centres at integers), so a resize is exact. The one home of the rescale;
    focal lengths scale by ``scale`` alone (``rescaled_k``)."""
    return scale * (np.asarray(px, dtype=np.float64) + 0.5) - 0.5


def rescaled_k(k: np.ndarray, scale: float) -> np.ndarray:
    """(..., 4) (fx, fy, cx, cy) px -> the same camera's in the image resized ``scale`` times per side."""
    k = np.asarray(k, dtype=np.float64)
    return np.concatenate([scale * k[..., :2], rescaled_px(k[..., 2:], scale)], axis=-1)


def to_camera(points_3d: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """{W} points (..., N, 3) in mm -> {C} points (..., N, 3) in mm for poses (..., 3)."""
    R = rvec_to_matrix(rvec)
    return np.asarray(points_3d) @ np.swapaxes(R, -1, -2) + np.asarray(tvec)[..., None, :]


def project_camera(K: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """{C} points (..., N, 3) in mm -> pixels (..., N, 2) under K (..., 3, 3)."""
    p = k_params(K)[..., None, :]
    z = points_cam[..., 2]
    return np.stack(
        [p[..., 0] * points_cam[..., 0] / z + p[..., 2], p[..., 1] * points_cam[..., 1] / z + p[..., 3]],
        axis=-1,
    )


def project(points_3d: np.ndarray, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """{W} points (..., N, 3) in mm -> pixels (..., N, 2) under K and the pose {W}->{C}."""
    return project_camera(K, to_camera(points_3d, rvec, tvec))


def camera_xy_inverse_depth(points_3d: np.ndarray, R: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """One frame's {W} points (N, 3) mm -> (3, N) rows X_C, Y_C (mm) and 1 / Z_C (1/mm) of the
    {C} points X_C = R X + t, R (3, 3) (the layout of the grid feature's point rows 2-4), in
    ``camera_rows``'s order."""
    rows = camera_rows(points_3d, R, tvec)
    np.divide(1.0, rows[2], out=rows[2])
    return rows


def reprojection_residuals(
    points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray, R: np.ndarray, tvec: np.ndarray
) -> np.ndarray:
    """The reprojection residuals pi(K (R X + t)) - x, coordinate-major: points_2d (..., N, 2) px,
    points_3d (..., N, 3) mm in {W}, K (..., 3, 3) px, the pose {W}->{C} as rotation matrices R
    (..., 3, 3) and tvec (..., 3) mm -> (..., 2, N) px (the u row, then the v row).

    The one residual of the runtime's batched code (``project`` gives the pixels themselves);
    coordinate-major, as it is faster than through ``project`` (models_spec/BENCHMARKS.md)."""
    K = np.asarray(K, dtype=np.float64)
    Xc = np.matmul(R, np.swapaxes(points_3d, -1, -2))  # (..., 3, N)
    Xc += np.asarray(tvec, dtype=np.float64)[..., :, None]
    # fx X / Z + cx - x and fy Y / Z + cy - y, in the order of operations of project().
    d = np.multiply(Xc[..., :2, :], np.stack([K[..., 0, 0], K[..., 1, 1]], -1)[..., :, None])
    d /= Xc[..., 2:, :]
    d += K[..., :2, 2:]
    d -= np.swapaxes(points_2d, -1, -2)
    return d


def residual_norms(residuals: np.ndarray) -> np.ndarray:
    """(..., 2, N) px residual rows (u, then v) -> (..., N) their Euclidean norms (px). As
    sqrt(u^2 + v^2), a third of np.hypot's time; hypot's guard against overflow is moot for pixel
    residuals."""
    u, v = residuals[..., 0, :], residuals[..., 1, :]
    return np.sqrt(u * u + v * v)


def reprojection_errors(points_2d, points_3d, K, rvec, tvec) -> np.ndarray:
    """Euclidean reprojection error (px) of each correspondence: points_2d (..., N, 2) px,
    points_3d (..., N, 3) mm, K (..., 3, 3), pose rvec, tvec (..., 3) {W}->{C} -> (..., N)."""
    return residual_norms(reprojection_residuals(points_2d, points_3d, K, rotation_matrices(rvec), tvec))


def mean_reprojection_error(points_2d, points_3d, valid, K, rvec, tvec) -> np.ndarray:
    """Mean Euclidean reprojection error (px) of B frames over their valid points: points_2d
    (B, N, 2) px, points_3d (B, N, 3) mm, valid (B, N) bool or None (all points), K (3, 3) or
    (B, 3, 3) px, the poses {W}->{C} rvec (B, 3) rad and tvec (B, 3) mm -> (B,) px. Invalid
    points' values are ignored (they may be NaN)."""
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        points_2d = np.where(valid[..., None], points_2d, 0.0)
        points_3d = np.where(valid[..., None], points_3d, 1.0)
    R = rotation_matrices(np.asarray(rvec, dtype=np.float64).reshape(-1, 3))
    d = reprojection_residuals(points_2d, points_3d, K, R, np.asarray(tvec, dtype=np.float64).reshape(-1, 3))
    return mean_residual_norms(d, valid)


def min_depths(points_3d, valid, rvec, tvec) -> np.ndarray:
    """The smallest depth Z_C (mm) of each of B frames' valid points at its pose {W}->{C}:
    points_3d (B, N, 3) mm, valid (B, N) bool or None (all), rvec, tvec (B, 3) -> (B,); <= 0
    when a point lies behind the camera."""
    R = rotation_matrices(np.asarray(rvec, dtype=np.float64).reshape(-1, 3))
    z = (np.asarray(points_3d) @ R[:, 2, :, None])[..., 0] + np.asarray(tvec, dtype=np.float64).reshape(-1, 3)[:, 2:]
    return np.min(z, axis=1, where=True if valid is None else valid, initial=np.inf)


def mean_over(values: np.ndarray, valid) -> np.ndarray:
    """(..., N) values -> (...,) their mean over the ``valid`` (..., N) bool entries, or over all
    entries when valid is None."""
    if valid is None:
        return values.sum(-1) / values.shape[-1]
    return np.where(valid, values, 0.0).sum(-1) / valid.sum(-1)


def mean_residual_norms(residuals: np.ndarray, valid) -> np.ndarray:
    """(B, 2, N) px residual rows (u, then v) of B frames -> (B,) their mean Euclidean norm (px)
    over the ``valid`` (B, N) bool points (None: all)."""
    return mean_over(residual_norms(residuals), valid)


def camera_centre(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(3,) camera centre in {W} (mm) of the pose {W}->{C}."""
    return -rvec_to_matrix(rvec).T @ tvec


def facing(points_mm: np.ndarray, normals: np.ndarray, camera_mm: np.ndarray) -> np.ndarray:
    """(N,) whether each surface point's outward normal points towards the camera."""
    return np.einsum("ni,ni->n", camera_mm - points_mm, normals) > 0


def frame_residuals(
    points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray, R: np.ndarray, tvec: np.ndarray
) -> np.ndarray:
    """One frame's reprojection residuals pi(K (R X + t)) - x, (N, 2) px: points_2d (N, 2) px,
    points_3d (N, 3) mm float64, the pose {W}->{C} as R (3, 3) and tvec (3,) mm. The hot path's
    twin of ``reprojection_residuals`` through OpenCV: 8 against 21 µs at 320 points
    (models_spec/BENCHMARKS.md)."""
    d = cv2.convertPointsFromHomogeneous(_homogeneous_pixels(points_3d, K, R, tvec)).reshape(-1, 2)
    d -= points_2d
    return d


def _homogeneous_pixels(points_3d: np.ndarray, K: np.ndarray, R: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(N, 1, 3) K (R X + t) of one frame's (N, 3) points through OpenCV: z (u, v, 1), z = Z_C."""
    Rt = np.empty((3, 4))
    Rt[:, :3], Rt[:, 3] = R, tvec
    return cv2.transform(points_3d.reshape(-1, 1, 3), K @ Rt)


def frame_mean_norm(residuals: np.ndarray) -> float:
    """Mean Euclidean norm (px) of one frame's (2, N) residuals (u row, v row). The hot path's twin
    of ``mean_residual_norms``: its norms sqrt(u u + v v) to the bit, summed by OpenCV's float64 loop
    (no IPP path), 3.4 against 7 µs at 320 points (models_spec/BENCHMARKS.md).

    Not cv2.magnitude: through IPP it rounds u u + v v once (FMA) or twice depending on where its output
    buffer lies (64-byte alignment), which malloc decides differently in each thread, so one frame's
    error changed in the last bit from thread to thread. Each step here is rounded as IEEE says
    whatever the buffers (issue 48: results bit-identical whatever the threads)."""
    squares = np.square(residuals)
    norms = np.add(squares[0], squares[1])  # contiguous, as OpenCV takes it without a copy
    return cv2.sumElems(np.sqrt(norms, out=norms))[0] / residuals.shape[1]


def frame_error_and_depth(points_2d, points_3d, K, rvec, tvec) -> tuple[float, float]:
    """One frame's mean Euclidean reprojection error (px) of its (N, 2) px / (N, 3) mm points under
    the pinhole K (3, 3) px (fx, skew, cx; fy, cy) at the pose rvec, tvec (3,), and the smallest depth
    Z_C of its points (mm, <= 0: a point behind the camera; NaN when one is NaN).

    In an order fixed here (``camera_rows``, ``pinhole_residuals``, then ``frame_mean_norm``), which the
    compiled core follows to the bit (``native.frame_error_and_depth``, the check stage's)."""
    rows = camera_rows(points_3d, cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0], tvec)
    depth = float(rows[2].min()) if rows.shape[1] else np.inf
    np.divide(1.0, rows[2], out=rows[2])
    return frame_mean_norm(pinhole_residuals(rows, points_2d, K)), depth


def camera_rows(points_3d: np.ndarray, R, t) -> np.ndarray:
    """(3, N) X_C, Y_C, Z_C (mm) of one frame's (N, 3) {W} points at the pose R (3, 3), t (3,):
    ((R_i0 X + R_i1 Y) + R_i2 Z) + t_i, elementwise (the compiled core's order)."""
    rows = rotated(R, np.array(points_3d.T, dtype=np.float64))  # of the coordinate rows
    rows += np.reshape(t, (3, 1))
    return rows


def pinhole_residuals(rows: np.ndarray, points_2d: np.ndarray, K) -> np.ndarray:
    """(2, N) residuals (a fx (+ b skew) + cx) - x and (b fy + cy) - y (px) of ``camera_rows`` whose
    last row holds 1 / Z_C already, a = X_C / Z_C, b = Y_C / Z_C, under the pinhole K (3, 3) px (the
    skew's term only where it is not 0)."""
    r = np.multiply(rows[:2], rows[2])
    skew = float(K[0][1])
    b_skew = r[1] * skew if skew else None
    K = np.asarray(K, dtype=np.float64)
    r *= K[(0, 1), (0, 1), None]
    if skew:
        r[0] += b_skew
    r += K[:2, 2:]
    r -= points_2d.T
    return r
