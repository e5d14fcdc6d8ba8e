"""The paper's accuracy metric: e(K) per frame, and the reduction ratio rho.

For a given K, a frame's pose is the PnP optimum on all its valid points with K fixed,
and e(K) is the mean Euclidean reprojection error (px) there. e_c = e(K_c),
e = e(K predicted), e* = the joint (K*, pose) fit's error. Over a set of frames,
rho = (Avg(e_c) - Avg(e)) / (Avg(e_c) - Avg(e*)): 0 means no better than K_c,
1 means as good as per-frame calibration.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from dimenet.runtime.geometry import mean_reprojection_error, solve_pnp


def reprojection_error_under_k(points_2d, points_3d, valid, K) -> np.ndarray:
    """e(K) (px) of each of F frames: K (F, 3, 3) or (3, 3) shared; pose by PnP on the valid points."""
    F = len(points_2d)
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (F, 3, 3))
    res = solve_pnp(points_2d, points_3d, valid, K)
    return mean_reprojection_error(points_2d, points_3d, valid, K, res.rvec, res.tvec)


def reduction_ratio(avg_e_c: float, avg_e: float, avg_e_star: float) -> Optional[float]:
    """rho; None when K_c already matches the oracle (no room to improve, rho undefined)."""
    gap = avg_e_c - avg_e_star
    if not np.isfinite(gap) or gap <= 1e-12:
        return None
    return float((avg_e_c - avg_e) / gap)
