"""The paper's accuracy metric: e(K) per frame, and the reduction ratio rho.

For a given K, a frame's pose is the PnP optimum on all its valid points with K fixed,
and e(K) is the mean Euclidean reprojection error (px) there. e_c = e(K_c),
e = e(K predicted), e* = the joint (K*, pose) fit's error. Over a set of frames,
rho = (Avg(e_c) - Avg(e)) / (Avg(e_c) - Avg(e*)): 0 means no better than K_c,
1 means as good as per-frame calibration. On a frame of one plane K is not observable and e*
does not exist; the homography floor (``geometry.homography_floor``) stands in for it.

rho has no meaning when its denominator is within the noise of the errors themselves: each
e(K) is a mean over the frame's points, whose standard error is s_f = std(point errors) /
sqrt(N_f); Avg over F frames has sqrt(sum s_f^2) / F. ``reduction_ratio`` is None (printed
"n/a") when Avg(e_c) - Avg(e*) is at most RHO_NOISE times that of Avg(e_c).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dimenet.runtime.geometry import mean_reprojection_error, reprojection_errors, solve_pnp

# rho's denominator must exceed this many standard errors of Avg(e_c) (module docstring).
RHO_NOISE = 2.0


def reprojection_error_under_k(points_2d, points_3d, valid, K) -> np.ndarray:
    """e(K) (px) of each of F frames: K (F, 3, 3) or (3, 3) shared; pose by PnP on the valid points."""
    return reprojection_error_and_variance(points_2d, points_3d, valid, K)[0]


def reprojection_error_and_variance(points_2d, points_3d, valid, K) -> tuple[np.ndarray, np.ndarray]:
    """e(K) (px) of each of F frames and the variance (px^2) of that mean: the variance of the
    frame's point errors over its N_f valid points, / N_f."""
    F = len(points_2d)
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (F, 3, 3))
    res = solve_pnp(points_2d, points_3d, valid, K)
    e = mean_reprojection_error(points_2d, points_3d, valid, K, res.rvec, res.tvec)
    p2, p3 = np.where(valid[..., None], points_2d, 0.0), np.where(valid[..., None], points_3d, 1.0)
    norms = reprojection_errors(p2, p3, K, res.rvec, res.tvec)
    n = valid.sum(1)
    spread = np.where(valid, (norms - e[:, None]) ** 2, 0.0).sum(1) / np.maximum(n - 1, 1)
    return e, spread / np.maximum(n, 1)


def average_noise(variances: np.ndarray) -> float:
    """The standard error (px) of an average of frame errors from their variances (px^2)."""
    return float(np.sqrt(np.sum(variances)) / len(variances))


def reduction_ratio(avg_e_c: float, avg_e: float, avg_e_star: float, noise_px: float = 0.0) -> Optional[float]:
    """rho; None when Avg(e_c) - Avg(e*) is at most RHO_NOISE times ``noise_px`` (the standard
    error of Avg(e_c), ``average_noise``) or 1e-12 px: no room to improve that the errors could
    show, rho undefined."""
    gap = avg_e_c - avg_e_star
    if not np.isfinite(gap) or gap <= max(RHO_NOISE * noise_px, 1e-12):
        return None
    return float((avg_e_c - avg_e) / gap)


# The interval of a ratio of rhos: its level, its bootstrap draws and their fixed seed (same frames, same interval).
RATIO_LEVEL = 0.9
RATIO_DRAWS = 2000
RATIO_SEED = 0


@dataclass(frozen=True)
class RatioInterval:
    """rho_method / rho_reference over a set of frames and its bootstrap interval (low, high) at ``level``; None
    where the reference does not improve on K_c (its rho is 0 or less there: no ratio), or the interval where more
    than the interval's tail share of the draws has no ratio."""

    ratio: Optional[float]
    low: Optional[float]
    high: Optional[float]
    level: float
    n_frames: int


def ratio_interval(
    e_c: np.ndarray,
    e: np.ndarray,
    e_reference: np.ndarray,
    *,
    level: float = RATIO_LEVEL,
    draws: int = RATIO_DRAWS,
    seed: int = RATIO_SEED,
) -> RatioInterval:
    """rho / rho_reference of a method of per-frame errors e (F,) px against a reference's e_reference (F,), both
    measured with e_c (F,): (Avg(e_c) - Avg(e)) / (Avg(e_c) - Avg(e_reference)) (e* cancels), and its percentile
    bootstrap interval at ``level`` over ``draws`` resamplings of the frames (the same frames for both: paired)."""
    e_c, e, e_ref = (np.asarray(a, dtype=np.float64) for a in (e_c, e, e_reference))
    n = len(e_c)
    if n == 0 or e.shape != (n,) or e_ref.shape != (n,) or e_c.shape != (n,):
        raise ValueError(f"ratio_interval: e_c, e and e_reference must be (F,) of one F >= 1, got {len(e_c)} frames")
    gain, room = float(np.mean(e_c - e)), float(np.mean(e_c - e_ref))
    ratio = gain / room if room > 0 else None
    idx = np.random.default_rng(seed).integers(0, n, (draws, n))
    gains, rooms = (e_c - e)[idx].mean(1), (e_c - e_ref)[idx].mean(1)
    tail = (1.0 - level) / 2.0
    if ratio is None or np.mean(rooms <= 0) > tail:
        return RatioInterval(ratio, None, None, level, n)
    ok = rooms > 0  # the draws where the reference improves on K_c (a ratio exists)
    low, high = np.quantile(gains[ok] / rooms[ok], [tail, 1.0 - tail])
    return RatioInterval(ratio, float(low), float(high), level, n)
