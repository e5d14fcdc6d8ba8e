"""The pose under a K close to the one a start pose was solved under: Gauss-Newton steps from it.

The rectifier's pose under the candidate K = K_c + Delta K (stage ``pnp_k``) starts from the C0 pose,
SQPnP's under K_c: Delta K is a few px, so the least-squares pose under K is a short step away.
``pose_steps`` takes POSE_STEPS Gauss-Newton steps of the reprojection error over the pose perturbed
on the left (``frame_normal_equations``'s 6 pose parameters; the pose block alone, ``pose_normal_equations``:
40 sums over the points where the monomials' Gram takes 66 and a 10 x 10 product), the rotation carried as a
unit quaternion between steps (no matrix logarithm, so no branch near pi).

Everything is in an order fixed here: elementwise numpy, numpy's pairwise sums along contiguous rows,
Python's float arithmetic and libm (math) for the 6 x 6 solve and the rotation, so that the compiled
core (runtime/native, ``dimenet_pose_steps``) computes the same pose to the bit (tests/native).
Where a rule would refuse K at this pose, the rectifier tries SQPnP's (``rectify.check_stage.frame_check``). The
figures against SQPnP under K: BENCHMARKS.md ("The pose under K")."""

from __future__ import annotations

import math

import cv2
import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry.projection import camera_rows, frame_error_and_depth, k_matrix, pinhole_residuals

# Gauss-Newton steps from the start pose: after 2, e(K) is within 3e-5 px of the converged least-squares
# pose's on the bench's frames (a third moves it by 1e-7 px for 9 us more; BENCHMARKS.md).
POSE_STEPS = 2
# Below this angle (rad) a rotation's quaternion <-> axis-angle use the series (sin x / x ~ 1 - x^2 / 6).
SMALL_ANGLE = 1e-8
NO_POSE_STEP = "no Gauss-Newton step: the points fix no pose under K"
# The pose's Jacobian per point over (w (3) rad, tau (3) mm), perturbed on the left, a = X/Z, b = Y/Z:
# du/dp = fx g_u, g_u = (-ab, 1 + a^2, -b, 1/Z, 0, -a/Z); dv/dp = fy g_v, g_v = (-1 - b^2, ab, a, 0, 1/Z, -b/Z).
# ``pose_normal_equations`` stacks the non-zero entries (rows 0-4: g_u at POSE_U, rows 5-9: g_v at POSE_V) and the
# residuals (rows 10, 11) and sums these products of its rows: the upper triangles of the u and the v block, then
# each block's rows times its residual.
POSE_U, POSE_V = (0, 1, 2, 3, 5), (0, 1, 2, 4, 5)
_U_PAIRS = [(i, j) for i in range(5) for j in range(i, 5)]
_PAIRS = np.array(
    [*_U_PAIRS, *[(5 + i, 5 + j) for i, j in _U_PAIRS], *[(i, 10) for i in range(5)], *[(5 + i, 11) for i in range(5)]]
).T


def quaternion(rvec) -> tuple:
    """Axis-angle (3,) rad -> the unit quaternion (w, x, y, z) of the same rotation."""
    rx, ry, rz = rvec
    theta = math.sqrt(rx * rx + ry * ry + rz * rz)
    if theta < SMALL_ANGLE:
        s = 0.5 - theta * theta / 48.0
        return 1.0 - theta * theta / 8.0, rx * s, ry * s, rz * s
    s = math.sin(0.5 * theta) / theta
    return math.cos(0.5 * theta), rx * s, ry * s, rz * s


def axis_angle(q) -> tuple:
    """A unit quaternion (w, x, y, z) -> axis-angle (3,) rad, angle in [0, pi]."""
    w, x, y, z = q
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(x * x + y * y + z * z)
    if n < SMALL_ANGLE:
        s = 2.0 / w
    else:
        s = 2.0 * math.atan2(n, w) / n
    return x * s, y * s, z * s


def compose(a, b) -> tuple:
    """The quaternion of rotation a after rotation b: a b."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        ((aw * bw - ax * bx) - ay * by) - az * bz,
        ((aw * bx + ax * bw) + ay * bz) - az * by,
        ((aw * by - ax * bz) + ay * bw) + az * bx,
        ((aw * bz + ax * by) - ay * bx) + az * bw,
    )


def pose_normal_equations(rows: np.ndarray, residuals: np.ndarray, fx: float, fy: float) -> tuple[list, list]:
    """J J^T (6, 6) and J r (6,) of the pose (perturbed on the left) under the focal lengths fx, fy (px) from
    ``camera_rows`` whose last row holds 1 / Z_C already and the residuals (2, N) px there (``pinhole_residuals``):
    JJ = fx^2 S_u + fy^2 S_v and Jr = fx R_u + fy R_v, S and R the pairwise sums of the products of g_u, g_v and the
    residuals (``_PAIRS``), as nested lists of floats."""
    a, b = np.multiply(rows[:2], rows[2])
    E = np.empty((12, rows.shape[1]))
    np.multiply(a, b, out=E[6])
    np.negative(E[6], out=E[0])
    np.multiply(a, a, out=E[1])
    E[1] += 1.0
    np.negative(b, out=E[2])
    E[3] = E[8] = rows[2]
    np.multiply(a, rows[2], out=E[4])
    np.negative(E[4], out=E[4])
    np.multiply(b, b, out=E[5])
    E[5] += 1.0
    np.negative(E[5], out=E[5])
    E[7] = a
    np.multiply(b, rows[2], out=E[9])
    np.negative(E[9], out=E[9])
    E[10:] = residuals
    sums = np.multiply(E[_PAIRS[0]], E[_PAIRS[1]]).sum(1).tolist()
    S_u, S_v = [[0.0] * 6 for _ in range(6)], [[0.0] * 6 for _ in range(6)]
    for n, (i, j) in enumerate(_U_PAIRS):
        S_u[POSE_U[i]][POSE_U[j]] = S_u[POSE_U[j]][POSE_U[i]] = sums[n]
        S_v[POSE_V[i]][POSE_V[j]] = S_v[POSE_V[j]][POSE_V[i]] = sums[15 + n]
    R_u, R_v = [0.0] * 6, [0.0] * 6
    for i in range(5):
        R_u[POSE_U[i]], R_v[POSE_V[i]] = sums[30 + i], sums[35 + i]
    fx2, fy2 = fx * fx, fy * fy
    JJ = [[fx2 * S_u[i][j] + fy2 * S_v[i][j] for j in range(6)] for i in range(6)]
    return JJ, [fx * R_u[i] + fy * R_v[i] for i in range(6)]


def solve_pose_step(H: list, g: list) -> list:
    """The Gauss-Newton step -H^-1 g of the normal equations H (6, 6), g (6,) (nested lists of floats) by Cholesky
    (L L^T, rows first to last); InputError when H is not positive definite (or not finite)."""
    L = [[0.0] * 6 for _ in range(6)]
    for i in range(6):
        for j in range(i + 1):
            s = H[i][j]
            for k in range(j):
                s -= L[i][k] * L[j][k]
            if i == j:
                if not s > 0.0 or s == math.inf:
                    raise InputError(NO_POSE_STEP)
                L[i][i] = math.sqrt(s)
            else:
                L[i][j] = s / L[j][j]
    y = [0.0] * 6
    for i in range(6):  # L y = -g
        s = -g[i]
        for k in range(i):
            s -= L[i][k] * y[k]
        y[i] = s / L[i][i]
    x = [0.0] * 6
    for i in range(5, -1, -1):  # L^T x = y
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k][i] * x[k]
        x[i] = s / L[i][i]
    return x


def pose_steps(points_2d, points_3d, k, rvec, tvec, steps: int = POSE_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """The pose {W}->{C} after ``steps`` Gauss-Newton steps of the reprojection error under the pinhole
    k = (fx, fy, cx, cy) px from the pose rvec (3,) rad, tvec (3,) mm: one frame's (N, 2) px and
    (N, 3) mm points (float64). -> rvec, tvec (3,); InputError when a step has no solution or the pose
    it reaches is not finite (no step: the start pose as it is). The residuals are
    ``frame_error_and_depth``'s (``camera_rows``, ``pinhole_residuals``)."""
    fx, fy = float(k[0]), float(k[1])
    K = k_matrix(k)
    q = quaternion([float(v) for v in rvec])
    t = [float(v) for v in tvec]
    r_now = np.asarray(rvec, dtype=np.float64).ravel()
    for _ in range(steps):
        rows = camera_rows(points_3d, cv2.Rodrigues(r_now)[0].tolist(), t)
        np.divide(1.0, rows[2], out=rows[2])
        step = solve_pose_step(*pose_normal_equations(rows, pinhole_residuals(rows, points_2d, K), fx, fy))
        w = step[:3]
        dR = cv2.Rodrigues(np.array(w))[0].tolist()
        t = [((dR[i][0] * t[0] + dR[i][1] * t[1]) + dR[i][2] * t[2]) + step[3 + i] for i in range(3)]
        q = compose(quaternion(w), q)
        r_now = np.array(axis_angle(q))
    t = np.array(t)
    if steps and not (np.isfinite(r_now).all() and np.isfinite(t).all()):
        raise InputError(NO_POSE_STEP)
    return r_now, t


def pose_under_k(points_2d, points_3d, k, rvec, tvec, steps: int = POSE_STEPS) -> tuple:
    """``pose_steps`` and ``frame_error_and_depth`` at the pose it reaches under K = k_matrix(k):
    (rvec, tvec, e px, smallest depth mm) (the compiled core's ``dimenet_pose_steps`` in one call)."""
    rvec, tvec = pose_steps(points_2d, points_3d, k, rvec, tvec, steps)
    return (rvec, tvec, *frame_error_and_depth(points_2d, points_3d, k_matrix(k), rvec, tvec))
