"""The pose under a K close to the one a start pose was solved under: Gauss-Newton steps from it.

The rectifier's pose under the candidate K = K_c + Delta K (stage ``pnp_k``) starts from the C0 pose,
SQPnP's under K_c: Delta K is a few px, so the least-squares pose under K is a short step away.
``pose_steps`` takes POSE_STEPS Gauss-Newton steps of the reprojection error over the pose perturbed
on the left (``frame_normal_equations``'s 6 pose parameters, from ``monomial_gram``), the rotation
carried as a unit quaternion between steps (no matrix logarithm, so no branch near pi).

Everything is in an order fixed here: elementwise numpy, numpy's pairwise sums (``monomial_gram``),
Python's float arithmetic and libm (math) for the 6 x 6 solve and the rotation, so that the compiled
core (runtime/native, ``dimenet_pose_steps``) computes the same pose to the bit (tests/native).
Where a rule would refuse K at this pose, the rectifier tries SQPnP's (``rectify.check_stage.frame_check``). The
figures against SQPnP under K: BENCHMARKS.md ("The pose under K")."""

from __future__ import annotations

import math

import cv2
import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry.normal_equations import gram_normal_equations, monomial_gram
from dimenet.runtime.geometry.projection import camera_rows, frame_error_and_depth, k_matrix, pinhole_residuals

# Gauss-Newton steps from the start pose: after 2, e(K) is within 3e-5 px of the converged least-squares
# pose's on the bench's frames (a third moves it by 1e-7 px for 9 us more; BENCHMARKS.md).
POSE_STEPS = 2
# Below this angle (rad) a rotation's quaternion <-> axis-angle use the series (sin x / x ~ 1 - x^2 / 6).
SMALL_ANGLE = 1e-8
NO_POSE_STEP = "no Gauss-Newton step: the points fix no pose under K"


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


def solve_pose_step(JJ: np.ndarray, Jr: np.ndarray) -> list:
    """The Gauss-Newton step -(JJ[:6, :6])^-1 Jr[:6] by Cholesky (L L^T, rows first to last);
    InputError when the pose block is not positive definite (or not finite)."""
    H = JJ[:6, :6].tolist()
    g = Jr[:6].tolist()
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
        JJ, Jr, _ = gram_normal_equations(monomial_gram(rows, pinhole_residuals(rows, points_2d, K)), fx, fy)
        step = solve_pose_step(JJ, Jr)
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
