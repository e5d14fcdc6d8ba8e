"""Pinhole geometry: the one home of projection, rotation and pose helpers.

Conventions (OpenCV): ``K`` is a 3x3 float64 matrix in pixels with zero skew,
``rvec`` is an axis-angle rotation (rad) and ``tvec`` a translation (mm) taking
points from the world frame {W} into the camera frame {C}: X_C = R(rvec) X_W + tvec.
Pixels are x right, y down, origin at the centre of the top-left pixel.

Every function is pure and accepts leading batch dimensions where noted.
"""
from __future__ import annotations

import cv2
import numpy as np

from .errors import CalibrationError, InputError

# Smallest depth (mm) a point may have in front of the camera and still be projected.
MIN_DEPTH_MM = 1e-6
# Up to this many poses, rotation_matrices calls cv2.Rodrigues pose by pose.
FEW_POSES = 8
_COVARIANCE = cv2.COVAR_NORMAL | cv2.COVAR_ROWS | cv2.COVAR_SCALE  # sample covariance of row points


def k_params(K: np.ndarray) -> np.ndarray:
    """(..., 3, 3) intrinsic matrices -> (..., 4) as (fx, fy, cx, cy) in pixels."""
    K = np.asarray(K, dtype=np.float64)
    return np.stack([K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]], axis=-1)


def k_matrix(params: np.ndarray) -> np.ndarray:
    """(..., 4) (fx, fy, cx, cy) in pixels -> (..., 3, 3) zero-skew intrinsic matrices."""
    params = np.asarray(params, dtype=np.float64)
    K = np.zeros(params.shape[:-1] + (3, 3))
    K[..., 0, 0] = params[..., 0]
    K[..., 1, 1] = params[..., 1]
    K[..., 0, 2] = params[..., 2]
    K[..., 1, 2] = params[..., 3]
    K[..., 2, 2] = 1.0
    return K


def frame_k_matrix(params) -> np.ndarray:
    """``k_matrix`` of one frame's (fx, fy, cx, cy) px in one numpy call (the runtime's hot path)."""
    fx, fy, cx, cy = params
    return np.array(((fx, 0.0, cx), (0.0, fy, cy), (0.0, 0.0, 1.0)))


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices, skew(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def rvec_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle (rad) -> (..., 3, 3) rotation matrices (Rodrigues' formula)."""
    rvec = np.asarray(rvec, dtype=np.float64)
    theta = np.linalg.norm(rvec, axis=-1)[..., None, None]
    S = skew(rvec)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * S + b * (S @ S)


def rotation_matrices(rvec: np.ndarray) -> np.ndarray:
    """``rvec_to_matrix`` (same values to float rounding), fast for a few poses: OpenCV's
    Rodrigues pose by pose below ``FEW_POSES`` poses, the vectorised formula above."""
    rvec = np.ascontiguousarray(rvec, dtype=np.float64)
    if rvec.shape == (1, 3):
        return cv2.Rodrigues(rvec[0])[0][None]
    if rvec.shape == (3,):
        return cv2.Rodrigues(rvec)[0]
    if rvec.ndim == 2 and len(rvec) <= FEW_POSES:
        return np.array([cv2.Rodrigues(r)[0] for r in rvec]).reshape(len(rvec), 3, 3)
    return rvec_to_matrix(rvec)


def matrix_to_rvec(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle (rad), angle in [0, pi]."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 3))
    for i, Ri in enumerate(flat):  # cv2 handles the angle-near-pi branch robustly
        out[i] = cv2.Rodrigues(Ri)[0].ravel()
    return out.reshape(R.shape[:-2] + (3,))


def to_camera(points_3d: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """{W} points (..., N, 3) in mm -> {C} points (..., N, 3) in mm for poses (..., 3)."""
    R = rvec_to_matrix(rvec)
    return np.einsum("...ij,...nj->...ni", R, points_3d) + np.asarray(tvec)[..., None, :]


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


def covariance_invariants(points: np.ndarray) -> tuple[float, float, float]:
    """Trace, sum of principal 2x2 minors and determinant of the sample covariance of one
    frame's (N, D) float64 C-contiguous points, D = 2 or 3 (units^2, ^4, ^(2D); OpenCV's
    covariance, then floats)."""
    C = cv2.calcCovarMatrix(points, None, _COVARIANCE)[0].tolist()  # symmetric
    if len(C) == 2:
        (a, b), (_, d) = C
        return a + d, a * d - b * b, a * d - b * b
    (a, b, c), (_, d, e), (_, _, f) = C
    det = a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c)
    return a + d + f, a * d - b * b + a * f - c * c + d * f - e * e, det


def covariance_invariants_batch(points: np.ndarray, mask) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``covariance_invariants`` of B frames at once (numpy): points (B, P, D) float64, D = 2 or
    3, mask (B, P) bool of the points to use (>= 1 per frame) or None (all) -> trace, sum of
    principal 2x2 minors and determinant, (B,) each."""
    T = np.ascontiguousarray(np.swapaxes(points, 1, 2))  # (B, D, P), coordinate-major
    if mask is not None:
        np.copyto(T, 0.0, where=~mask[:, None, :])
    n = np.full(len(T), T.shape[2], np.float64) if mask is None else mask.sum(1).astype(np.float64)
    T -= (T.sum(-1) / n[:, None])[:, :, None]
    if mask is not None:
        np.copyto(T, 0.0, where=~mask[:, None, :])
    C = np.matmul(T, np.swapaxes(T, 1, 2)) / n[:, None, None]
    D = points.shape[-1]
    minors = sum(C[:, i, i] * C[:, j, j] - C[:, i, j] * C[:, j, i] for i in range(D) for j in range(i + 1, D))
    return np.trace(C, axis1=1, axis2=2), minors, np.linalg.det(C)


def frame_residuals(points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray, R: np.ndarray,
                    tvec: np.ndarray) -> np.ndarray:
    """One frame's reprojection residuals pi(K, R X + t) - x (N, 2) px, through OpenCV (few calls,
    for the runtime's hot path): points_2d (N, 2) px, points_3d (N, 3) mm float64, pose {W}->{C}
    as the rotation matrix R (3, 3) and tvec (3,) mm."""
    Rt = np.empty((3, 4))
    Rt[:, :3], Rt[:, 3] = R, tvec
    d = cv2.convertPointsFromHomogeneous(cv2.transform(points_3d.reshape(-1, 1, 3), K @ Rt)).reshape(-1, 2)
    d -= points_2d
    return d


def camera_xy_inverse_depth(points_3d: np.ndarray, R: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """One frame's {W} points (N, 3) mm -> (3, N) rows X_C, Y_C (mm) and 1 / Z_C (1/mm) of the
    {C} points X_C = R X + t, R (3, 3) (the layout of the grid feature's point rows 2-4)."""
    Xc = R @ points_3d.T
    Xc += tvec.reshape(3, 1)
    np.divide(1.0, Xc[2], out=Xc[2])
    return Xc


def _jacobian_basis() -> np.ndarray:
    """(3, 20, 9): the rows of ``frame_normal_equations``'s coefficient matrix C (20 x 9) as
    C = fx B[0] + fy B[1] + B[2]. Row 2j + c (c = 0: u, 1: v) holds dr_c/dp_j in the basis
    q = [1, a, b, ab, a^2, b^2, 1/Z, a/Z, b/Z] of the point's normalised coordinates a = X/Z,
    b = Y/Z, for p = (w (3) rad, tau (3) mm, fx, fy, cx, cy) with the pose perturbed on the left."""
    B = np.zeros((3, 10, 2, 9))
    fx, fy, one = 0, 1, 2
    # du/dp = fx [-ab, 1 + a^2, -b, 1/Z, 0, -a/Z], then [a, 0, 1, 0] for (fx, fy, cx, cy).
    B[fx, 0, 0, 3], B[fx, 1, 0, 0], B[fx, 1, 0, 4], B[fx, 2, 0, 2] = -1.0, 1.0, 1.0, -1.0
    B[fx, 3, 0, 6], B[fx, 5, 0, 7], B[one, 6, 0, 1], B[one, 8, 0, 0] = 1.0, -1.0, 1.0, 1.0
    # dv/dp = fy [-1 - b^2, ab, a, 0, 1/Z, -b/Z], then [0, b, 0, 1].
    B[fy, 0, 1, 0], B[fy, 0, 1, 5], B[fy, 1, 1, 3], B[fy, 2, 1, 1] = -1.0, -1.0, 1.0, 1.0
    B[fy, 4, 1, 6], B[fy, 5, 1, 8], B[one, 7, 1, 2], B[one, 9, 1, 0] = 1.0, -1.0, 1.0, 1.0
    return B.reshape(3, 20 * 9)


_JACOBIAN_BASIS = _jacobian_basis()


def frame_normal_equations(xy_inv_z: np.ndarray, points_2d: np.ndarray,
                           k) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """One frame's Gauss-Newton normal equations under the pinhole (fx, fy, cx, cy) px ``k``.

    xy_inv_z (3, N): the points in {C} as X, Y (mm) and 1/Z (1/mm) (``camera_xy_inverse_depth``);
    points_2d (N, 2) px. With r the residuals pi(K, X_C) - x and J (10, 2N) their Jacobian for
    p = (w (3) rad, tau (3) mm, fx, fy, cx, cy), the pose perturbed on the left (X_C ->
    exp([w]x) X_C + tau, so R -> exp([w]x) R, t -> exp([w]x) t + tau), returns J J^T (10, 10),
    J r (10,), r.r (px^2) and r (2, N) px (the u residuals, then the v residuals).

    Every entry of J is a linear combination of nine per-point monomials q (see
    ``_jacobian_basis``), so J J^T = C (q q^T) C^T summed over u and v: one N-long product
    of an (11, N) array with itself (q and r) instead of forming J.
    """
    fx, fy, cx, cy = k
    Q = np.empty((11, xy_inv_z.shape[1]))  # q (9 rows), then r_u, r_v
    Q[6] = inv_z = xy_inv_z[2]
    ab = np.multiply(xy_inv_z[:2], inv_z, out=Q[1:3])  # a, b
    np.multiply(ab[0], ab[1], out=Q[3])
    np.multiply(ab, ab, out=Q[4:6])
    np.multiply(ab, inv_z, out=Q[7:9])
    Q[0] = 1.0
    r = np.multiply(ab, ((fx,), (fy,)), out=Q[9:])
    r += ((cx,), (cy,))
    r -= points_2d.T
    G = Q @ Q.T
    C = np.dot((fx, fy, 1.0), _JACOBIAN_BASIS).reshape(20, 9)
    # J J^T: sum over c in (u, v) and q of (C q q^T)[2i + c, q] C[2j + c, q]; J r likewise.
    JJ = (C @ G[:9, :9]).reshape(10, 18) @ C.reshape(10, 18).T
    Cr = C @ G[:9, 9:]
    return JJ, Cr[0::2, 0] + Cr[1::2, 1], float(G[9, 9] + G[10, 10]), r


def left_update(R: np.ndarray, tvec: np.ndarray, w: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose {W}->{C}, rotation matrix R (3, 3) and tvec (3,) mm, after the left perturbation
    (w rad, tau mm) of ``frame_normal_equations``: (exp([w]x) R, exp([w]x) t + tau)."""
    dR = cv2.Rodrigues(w)[0]
    return dR @ R, dR @ tvec + tau


def reprojection_errors(points_2d, points_3d, K, rvec, tvec) -> np.ndarray:
    """Euclidean reprojection error (px) of each correspondence, shape (..., N)."""
    return np.linalg.norm(project(points_3d, K, rvec, tvec) - points_2d, axis=-1)


def mean_reprojection_error(points_2d, points_3d, weights, K, rvec, tvec) -> np.ndarray:
    """Mean Euclidean reprojection error (px) over the points with weight > 0, shape (...)."""
    valid = np.asarray(weights) > 0
    err = reprojection_errors(np.where(valid[..., None], points_2d, 0.0),
                              np.where(valid[..., None], points_3d, 1.0), K, rvec, tvec)
    return mean_over(err, valid)


def mean_over(values: np.ndarray, valid) -> np.ndarray:
    """(..., N) values -> (...,) their mean over the ``valid`` (..., N) bool entries, or over all
    entries when valid is None."""
    if valid is None:
        return values.sum(-1) / values.shape[-1]
    return np.where(valid, values, 0.0).sum(-1) / valid.sum(-1)


def mean_residual_norms(residuals: np.ndarray, valid) -> np.ndarray:
    """(B, 2, N) px residual rows (u, then v) of B frames -> (B,) their mean Euclidean norm (px)
    over the ``valid`` (B, N) bool points (None: all). As sqrt(u^2 + v^2), a third of np.hypot's
    time; hypot's guard against overflow is moot for pixel residuals."""
    u, v = residuals[:, 0], residuals[:, 1]
    return mean_over(np.sqrt(u * u + v * v), valid)


def mean_reprojection_errors(points_2d, points_3d, valid, K, R, tvec) -> np.ndarray:
    """``mean_reprojection_error`` of B frames (same values to float rounding), computed
    coordinate-major for speed: points_2d (B, N, 2) px, points_3d (B, N, 3) mm, valid (B, N)
    bool or None for all points, K (3, 3) or (B, 3, 3), R (B, 3, 3) rotations and tvec (B, 3)
    mm of the poses {W}->{C}. Returns (B,) px."""
    if valid is not None:
        points_2d = np.where(valid[..., None], points_2d, 0.0)
        points_3d = np.where(valid[..., None], points_3d, 1.0)
    K = np.asarray(K, dtype=np.float64).reshape(-1, 3, 3)
    Xc = np.matmul(R, np.swapaxes(points_3d, 1, 2))  # (B, 3, N)
    Xc += np.asarray(tvec, dtype=np.float64)[:, :, None]
    # fx X / Z + cx - x and fy Y / Z + cy - y, in the order of operations of project().
    d = np.multiply(Xc[:, :2], np.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, :, None])
    d /= Xc[:, 2:]
    d += K[:, :2, 2:]
    d -= np.swapaxes(points_2d, 1, 2)
    return mean_residual_norms(d, valid)


def check_not_degenerate(points_3d: np.ndarray, points_2d: np.ndarray) -> None:
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


def solve_pnp_start(points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fast closed-form pose {W}->{C} (SQPnP) for one frame: (N, 2) px, (N, 3) mm -> rvec, tvec (3,).

    Raises InputError when OpenCV finds no pose.
    """
    ok, rvec, tvec = cv2.solvePnP(
        np.ascontiguousarray(points_3d, dtype=np.float64),
        np.ascontiguousarray(points_2d, dtype=np.float64),
        np.asarray(K, dtype=np.float64), None, flags=cv2.SOLVEPNP_SQPNP,
    )
    if not ok or not ((cv2.checkRange(rvec)[0] and cv2.checkRange(tvec)[0])  # fast; refuses +DBL_MAX too
                      or (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)))):
        raise InputError("PnP failed: no camera pose explains these correspondences")
    return rvec.ravel(), tvec.ravel()


def dlt_camera(points_2d: np.ndarray, points_3d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form K, rvec, tvec from >= 6 non-coplanar correspondences of one frame (DLT + RQ).

    Hartley-normalised direct linear transform of the 3x4 camera matrix, then an RQ
    decomposition; skew is dropped (the 4-parameter model). Raises CalibrationError
    when the 3D points are coplanar or too few, where K is not observable from one view.
    """
    n = len(points_3d)
    if n < 6:
        raise CalibrationError(f"K from one frame needs >= 6 points, got {n}")
    c3 = points_3d.mean(0)
    s3 = np.sqrt(3) / np.sqrt(((points_3d - c3) ** 2).sum(1).mean())
    sv = np.linalg.svd((points_3d - c3) * s3, compute_uv=False)
    if sv[2] < 0.05 * sv[0]:
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
