"""Poses from correspondences: the closed-form starts (SQPnP, DLT) and the degeneracy check."""

from __future__ import annotations

import math

import cv2
import numpy as np

from dimenet.runtime.errors import CalibrationError, InputError
from dimenet.runtime.geometry.projection import k_matrix, k_params
from dimenet.runtime.geometry.rotation import matrix_to_rvec
from dimenet.runtime.geometry.spread import spans_3d

# Fewest correspondences of a frame anywhere in dimenet: a pose and, from non-coplanar points,
# its K (the DLT's 11 unknowns need 6 points); datasets, the rectifier and the predictors ask
# for it.
MIN_POINTS = 6
# Fewest correspondences from which a pose alone is solved (SQPnP and the BPnP layer).
MIN_POSE_POINTS = 4
# The largest binary exponent of a finite float64 (2^1024 overflows).
MAX_EXPONENT = 1023


def check_not_degenerate(points_2d: np.ndarray, points_3d: np.ndarray) -> None:
    """Raise InputError when the correspondences cannot fix a pose.

    Rejects coincident or collinear 3D points (mm) and coincident image points (px).
    """
    for name, pts, unit in (("points_3d", points_3d, "mm"), ("points_2d", points_2d, "px")):
        centred = pts - pts.mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        scale = max(np.abs(pts).max(), 1.0)
        if sv[0] <= 1e-9 * scale:
            raise InputError(f"{name}: all points coincide ({unit}); a pose needs spread-out points")
        if sv[1] <= 1e-6 * sv[0]:
            raise InputError(f"{name}: all points are collinear; a pose needs points off one line")


def solve_pnp_start(
    points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray, unit: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Fast closed-form pose {W}->{C} (SQPnP) for one frame: (N, 2) px, (N, 3) mm -> rvec, tvec (3,).

    The 3D points are solved for in a unit of the power of two nearest their RMS norm (exact: the
    scaling changes no mantissa), and tvec scaled back: SQPnP's tolerances are absolute, so a scene
    in units of 1e-6 mm would otherwise get another pose than the same scene in mm. ``unit``: that
    power of two (mm) when the caller has it (``native.solve_pnp_start``: the compiled core's), else
    ``power_of_two_unit`` here.
    Raises InputError when OpenCV finds no pose or fails on the input.
    """
    points_3d = np.asarray(points_3d, dtype=np.float64)
    if unit is None:
        unit = power_of_two_unit(points_3d)
    try:
        ok, rvec, tvec = cv2.solvePnP(
            points_3d * (1.0 / unit),
            np.ascontiguousarray(points_2d, dtype=np.float64),
            np.asarray(K, dtype=np.float64),
            None,
            flags=cv2.SOLVEPNP_SQPNP,
        )
    except cv2.error as exc:
        raise InputError(f"PnP failed: OpenCV could not solve for a pose ({exc.err})") from None
    if not ok or not (
        (cv2.checkRange(rvec)[0] and cv2.checkRange(tvec)[0])  # fast; refuses +DBL_MAX too
        or (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)))
    ):
        raise InputError("PnP failed: no camera pose explains these correspondences")
    return rvec.ravel(), tvec.ravel() * unit


def power_of_two_unit(points_3d: np.ndarray) -> float:
    """The power of two nearest the RMS norm of (N, 3) points (1 when that is 0 or not finite; at most
    2^MAX_EXPONENT, the largest finite one); the points are taken over their largest coordinate first, so
    1e300 mm does not overflow. OpenCV's
    largest |coordinate| (exact, NaN refused by checkRange) and numpy's pairwise sum of squares, then
    Python's float math: the reference of the compiled core's ``dimenet_power_of_two_unit``
    (models_spec/BENCHMARKS.md has both's us)."""
    if points_3d.size and points_3d.dtype == np.float64 and cv2.checkRange(points_3d)[0]:
        largest = cv2.norm(points_3d, cv2.NORM_INF)
    else:
        largest = float(np.max(np.abs(points_3d))) if points_3d.size else 0.0
    if not (0.0 < largest < math.inf):
        return 1.0
    squares = points_3d / largest
    np.square(squares, out=squares)
    rms = largest * math.sqrt(float(squares.sum()) / squares.size * 3.0)
    if not 0.0 < rms < math.inf:  # a denormal largest coordinate can give 0
        return 1.0
    return math.ldexp(1.0, min(round(math.log2(rms)), MAX_EXPONENT))


def dlt_camera(points_2d: np.ndarray, points_3d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form K, rvec, tvec from >= 6 non-coplanar correspondences of one frame (DLT + RQ).

    Hartley-normalised direct linear transform of the 3x4 camera matrix, then an RQ
    decomposition; skew is dropped (the 4-parameter model). Raises CalibrationError
    when the 3D points are coplanar or too few, where K is not observable from one view.
    """
    n = len(points_3d)
    if n < MIN_POINTS:
        raise CalibrationError(f"K from one frame needs >= {MIN_POINTS} points, got {n}")
    c3 = points_3d.mean(0)
    s3 = np.sqrt(3) / np.sqrt(((points_3d - c3) ** 2).sum(1).mean())
    if not spans_3d((points_3d - c3) * s3):
        raise CalibrationError("the 3D points are (nearly) coplanar: K is not observable from one planar view")
    c2 = points_2d.mean(0)
    s2 = np.sqrt(2) / np.sqrt(((points_2d - c2) ** 2).sum(1).mean())
    T3 = np.diag([s3, s3, s3, 1.0])
    T3[:3, 3] = -s3 * c3
    T2 = np.diag([s2, s2, 1.0])
    T2[:2, 2] = -s2 * c2
    Xh = np.c_[(points_3d - c3) * s3, np.ones(n)]
    xn = (points_2d - c2) * s2
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xn[:, :1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xn[:, 1:] * Xh
    P = np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 4)
    P = np.linalg.inv(T2) @ P @ T3
    M = P[:, :3]
    if np.linalg.det(M) < 0:
        P, M = -P, -M
    # RQ decomposition of M = K R via QR of the row-reversed transpose.
    flip = np.eye(3)[::-1]
    Q, U = np.linalg.qr((flip @ M).T)
    Kr = flip @ U.T @ flip
    R = flip @ Q.T
    signs = np.diag(np.sign(np.diag(Kr)))
    Kr, R = Kr @ signs, signs @ R
    t = np.linalg.solve(Kr, P[:, 3])
    Kr = Kr / Kr[2, 2]
    if np.linalg.det(R) < 0:
        raise CalibrationError("DLT gave a reflection: the correspondences are inconsistent")
    return k_matrix(k_params(Kr)), matrix_to_rvec(R), t


def planar_focal(H: np.ndarray, centre_px: np.ndarray) -> float:
    """The focal length (px) one plane's homography H (3, 3), plane coordinates with square units -> px,
    gives a camera of square pixels and principal point ``centre_px`` (2,): the least-squares solution of
    Zhang's two constraints on 1/f² (the plane's axes orthogonal and of equal length). NaN where the view
    does not tell it (a plane seen face on, or constraints with no positive solution)."""
    shift = np.array([[1.0, 0.0, -centre_px[0]], [0.0, 1.0, -centre_px[1]], [0.0, 0.0, 1.0]])
    (a1, a2), (b1, b2), (c1, c2) = (shift @ np.asarray(H, np.float64))[:, :2]
    lhs = np.array([a1 * a2 + b1 * b2, a1 * a1 + b1 * b1 - a2 * a2 - b2 * b2])
    rhs = -np.array([c1 * c2, c1 * c1 - c2 * c2])
    inverse_f2 = float(lhs @ rhs) / float(lhs @ lhs) if lhs @ lhs > 0 else float("nan")
    return 1.0 / np.sqrt(inverse_f2) if inverse_f2 > 0 else float("nan")
