"""The network's uncertainty on Delta K: a 4x4 covariance (px^2) per frame.

Choice (models_spec/model-v1.md, "uncertainty"): not a second network head but a model of
the network's residuals, fitted after training on the early-stopping frames under the
training augmentation (fewer points, emptied cells, clustered noisy labels). It keeps the
network, and f(0) = 0 for the mean, untouched.

Per frame, three statistics of the inference points say how much the input can tell:
``n`` points, ``m`` occupied grid cells and ``d`` their mean PMD norm under K_c at the C0
pose (px). With z = [1, log n, log m, log max(d, D_FLOOR_PX)], each parameter's standard
deviation is sigma_p = exp(coef_p . z) (px), and the covariance is
diag(sigma) C diag(sigma) with one correlation matrix C. Fitting: per parameter, the
Gaussian maximum-likelihood coef on the residuals K - K* (Newton, convex), then its
intercept rescaled so that 68.27 % of the fitting frames lie within 1 sigma, then C from
the standardised residuals.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .geometry import mean_over

PARAMETERS = ("fx", "fy", "cx", "cy")
STATISTICS = ("log_points", "log_cells", "log_pmd")
D_FLOOR_PX = 0.05  # PMD below this says nothing more: noise-free frames are not infinitely certain
ONE_SIGMA = 0.6827  # share of a Gaussian within one standard deviation
RIDGE = 1e-6  # keeps the Newton steps of the fit defined when a statistic does not vary


@dataclass(frozen=True)
class Uncertainty:
    """coef (4, 4): per parameter (fx, fy, cx, cy), the weights of z = [1, log n, log m, log d];
    correlation (4, 4): of the standardised residuals."""

    coef: np.ndarray
    correlation: np.ndarray

    def to_dict(self) -> dict:
        return {"parameters": list(PARAMETERS), "statistics": ["1", *STATISTICS],
                "coef": self.coef.tolist(), "correlation": self.correlation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Uncertainty":
        coef = np.asarray(d["coef"], dtype=np.float64)
        corr = np.asarray(d["correlation"], dtype=np.float64)
        if coef.shape != (4, 4) or corr.shape != (4, 4) or not (np.all(np.isfinite(coef)) and np.all(np.isfinite(corr))):
            raise ValueError(f"uncertainty: coef and correlation must be finite 4x4, got {coef.shape} and {corr.shape}")
        if np.any(np.linalg.eigvalsh((corr + corr.T) / 2) <= 0):
            raise ValueError("uncertainty: the correlation matrix is not positive definite")
        return cls(coef=coef, correlation=corr)

    def sigma(self, stats: np.ndarray) -> np.ndarray:
        """(B, 3) frame statistics -> (B, 4) standard deviations of (fx, fy, cx, cy), px."""
        return np.exp(_design(stats) @ self.coef.T)

    def frame_covariance(self, n_points: int, occupied: int, mean_pmd_px: float) -> np.ndarray:
        """``covariance`` of one frame from its three numbers (the runtime's single-frame path)."""
        z = np.array((1.0, math.log(n_points), math.log(occupied), math.log(max(mean_pmd_px, D_FLOOR_PX))))
        s = np.exp(self.coef @ z)
        return np.outer(s, s) * self.correlation

    def covariance(self, stats: np.ndarray) -> np.ndarray:
        """(B, 3) frame statistics -> (B, 4, 4) covariance of Delta K, px^2."""
        s = self.sigma(stats)
        return s[:, :, None] * self.correlation * s[:, None, :]


def frame_statistics(n_points, occupied_cells, mean_pmd_px) -> np.ndarray:
    """(B, 3) [log n, log m, log max(d, D_FLOOR_PX)] from (B,) counts and mean PMD norms (px)."""
    n = np.asarray(n_points, dtype=np.float64)
    m = np.asarray(occupied_cells, dtype=np.float64)
    if np.any(n < 1) or np.any(m < 1):
        raise InputError("uncertainty: a frame needs >= 1 inference point in >= 1 cell")
    d = np.maximum(np.asarray(mean_pmd_px, dtype=np.float64), D_FLOOR_PX)
    return np.stack([np.log(n), np.log(m), np.log(d)], -1)


def occupied_cells(features: np.ndarray, n_channels: int) -> np.ndarray:
    """(B, D) grid features -> (B,) number of cells holding points (a zero cell is empty)."""
    return np.count_nonzero(features.reshape(len(features), -1, n_channels).any(-1), axis=-1)


def input_statistics(features: np.ndarray, pmd: np.ndarray, mask, n_channels: int) -> np.ndarray:
    """(B, 3) statistics of B frames' inference points from what the grid feature computes:
    features (B, D), pmd (B, 2, N) px the PMD rows (``grid_features(..., return_points=True)``
    points[:, :2]), mask (B, N) bool of the inference points or None (all)."""
    n = np.full(len(pmd), pmd.shape[2]) if mask is None else np.count_nonzero(mask, axis=1)
    return frame_statistics(n, occupied_cells(features, n_channels), mean_over(np.hypot(pmd[:, 0], pmd[:, 1]), mask))


def _design(stats: np.ndarray) -> np.ndarray:
    stats = np.asarray(stats, dtype=np.float64)
    return np.concatenate([np.ones((len(stats), 1)), stats], axis=1)


def _fit_log_sigma(z: np.ndarray, e: np.ndarray, iterations: int = 50) -> np.ndarray:
    """Maximum-likelihood w of e_i ~ N(0, exp(2 w.z_i)): Newton with step halving (the
    negative log-likelihood sum w.z + e^2 exp(-2 w.z) / 2 is convex in w)."""
    e2 = np.maximum(e**2, 1e-12)

    def nll(w):
        a = z @ w
        return float(np.sum(a + 0.5 * e2 * np.exp(-2 * a)))

    w = np.zeros(z.shape[1])
    w[0] = 0.5 * np.log(e2.mean())
    cost = nll(w)
    for _ in range(iterations):
        r = e2 * np.exp(-2 * (z @ w))
        grad = z.T @ (1.0 - r)
        hess = (z * (2 * r)[:, None]).T @ z + RIDGE * len(z) * np.eye(len(w))
        step = np.linalg.solve(hess, grad)
        for _ in range(30):
            new_cost = nll(w - step)
            if new_cost <= cost:
                break
            step = step / 2
        else:
            break
        w, gain, cost = w - step, cost - new_cost, new_cost
        if gain < 1e-10 * max(abs(cost), 1.0):
            break
    return w


def fit_uncertainty(residuals_px: np.ndarray, stats: np.ndarray) -> Uncertainty:
    """Fit the model to F frames' residuals K - K* (F, 4) px with their statistics (F, 3)."""
    residuals_px = np.asarray(residuals_px, dtype=np.float64)
    if residuals_px.ndim != 2 or residuals_px.shape[1] != 4 or len(residuals_px) != len(stats):
        raise InputError(f"uncertainty: residuals must be (F, 4) with F = {len(stats)}, got {residuals_px.shape}")
    if len(residuals_px) < 4 * (len(STATISTICS) + 1) or not np.all(np.isfinite(residuals_px)):
        raise InputError(f"uncertainty: needs >= {4 * (len(STATISTICS) + 1)} frames with finite residuals, "
                         f"got {len(residuals_px)}")
    z = _design(stats)
    coef = np.stack([_fit_log_sigma(z, residuals_px[:, p]) for p in range(4)])
    u = residuals_px / np.exp(z @ coef.T)
    coef[:, 0] += np.log(np.quantile(np.abs(u), ONE_SIGMA, axis=0))
    u = residuals_px / np.exp(z @ coef.T)
    second = u.T @ u / len(u)
    scale = np.sqrt(np.diag(second))
    return Uncertainty(coef=coef, correlation=second / np.outer(scale, scale))


def coverage(estimate_px: np.ndarray, truth_px: np.ndarray, covariance: np.ndarray) -> dict:
    """Share of frames with |estimate - truth| <= 1 sigma, per parameter: (F, 4), (F, 4), (F, 4, 4)."""
    sigma = np.sqrt(np.einsum("fii->fi", covariance))
    inside = np.abs(np.asarray(estimate_px) - np.asarray(truth_px)) <= sigma
    return {name: float(inside[:, p].mean()) for p, name in enumerate(PARAMETERS)}
