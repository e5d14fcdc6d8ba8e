"""Rotations: axis-angle rvec (rad) <-> 3x3 matrices, and the left pose update."""

from __future__ import annotations

import cv2
import numpy as np

# Up to this many poses, rotation_matrices calls cv2.Rodrigues pose by pose.
FEW_POSES = 8


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


def rotated(R, P: np.ndarray) -> np.ndarray:
    """R (3, 3) times P (3, M), each entry ((R_i0 P_0j + R_i1 P_1j) + R_i2 P_2j) elementwise: the compiled
    core's order (a BLAS product's summation order and fused multiply-adds depend on the machine)."""
    R = np.asarray(R, dtype=np.float64)
    out = np.multiply(R[:, :1], P[0])
    out += np.multiply(R[:, 1:2], P[1])
    out += np.multiply(R[:, 2:], P[2])
    return out


def left_update(R: np.ndarray, tvec: np.ndarray, w: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose {W}->{C}, rotation matrix R (3, 3) and tvec (3,) mm, after the left perturbation
    (w rad, tau mm) of ``frame_normal_equations``: (exp([w]x) R, exp([w]x) t + tau), the products in
    ``rotated``'s order."""
    dR = cv2.Rodrigues(np.asarray(w, dtype=np.float64))[0]
    t = rotated(dR, np.reshape(tvec, (3, 1))).ravel()
    t += tau
    return rotated(dR, R), t
