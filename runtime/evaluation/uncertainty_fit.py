"""Fitting the network's uncertainty model (``rectify.uncertainty.Uncertainty``) after training,
and measuring its 1 sigma coverage. The run-time half lives in ``dimenet.runtime.rectify.uncertainty``."""

from __future__ import annotations

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.rectify.uncertainty import MAX_DATA_BIAS, NOISE_SCALE_PX, PARAMETERS, STATISTICS, Uncertainty

ONE_SIGMA = 0.6827  # share of a Gaussian within one standard deviation
TWO_SIGMA = 0.9545  # ... and within two


RIDGE = 1e-6  # keeps the Newton steps of the fit defined when a statistic does not vary


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
    """Fit the model to F frames' residuals K - K* (F, 4) px with their statistics (F, 4)."""
    residuals_px = np.asarray(residuals_px, dtype=np.float64)
    if residuals_px.ndim != 2 or residuals_px.shape[1] != 4 or len(residuals_px) != len(stats):
        raise InputError(f"uncertainty: residuals must be (F, 4) with F = {len(stats)}, got {residuals_px.shape}")
    if len(residuals_px) < 4 * (len(STATISTICS) + 1) or not np.all(np.isfinite(residuals_px)):
        raise InputError(
            f"uncertainty: needs >= {4 * (len(STATISTICS) + 1)} frames with finite residuals, got {len(residuals_px)}"
        )
    stats = np.asarray(stats, dtype=np.float64)
    if stats.shape != (len(residuals_px), len(STATISTICS)):
        raise InputError(f"uncertainty: statistics must be (F, {len(STATISTICS)}), got {stats.shape}")
    z = np.c_[np.ones(len(stats)), stats]
    coef = np.stack([_fit_log_sigma(z, residuals_px[:, p]) for p in range(4)])
    u = residuals_px / np.exp(z @ coef.T)
    coef[:, 0] += np.log(np.quantile(np.abs(u), ONE_SIGMA, axis=0))
    u = residuals_px / np.exp(z @ coef.T)
    second = u.T @ u / len(u)
    scale = np.sqrt(np.diag(second))
    return Uncertainty(coef=coef, correlation=second / np.outer(scale, scale))


def _smallest_covering(covered, high: float, share: float = ONE_SIGMA) -> float:
    """The smallest x in [0, high] with covered(x) >= share (covered grows with x): 0 where
    covered(0) is, ``high`` where even covered(high) is not; bisection between."""
    low = 0.0
    if covered(low) >= share:
        return low
    if covered(high) < share:
        return high
    for _ in range(40):
        mid = (low + high) / 2
        low, high = (mid, high) if covered(mid) < share else (low, mid)
    return high


def _widened_variance(sigma_px, variance_ratio, noise_px, noise_scale_px: float, rho) -> np.ndarray:
    """(F, 4) px^2: the MAP posterior variance widened for the network's correlation rho (a number or
    (4,)) with the data, sigma^2 (1 + 2 rho w(s) sqrt(r (1 - r))) (``Uncertainty.posterior_scale``)."""
    w = noise_px**2 / (noise_px**2 + noise_scale_px**2)
    g = w[:, None] * np.sqrt(np.maximum(variance_ratio * (1.0 - variance_ratio), 0.0))
    return sigma_px**2 * (1.0 + 2.0 * np.asarray(rho) * g)


def _map_inputs(what: str, *arrays, noise_px) -> tuple:
    """The MAP errors' (F, 4) arrays and their noise (F,) as float64, checked (InputError naming ``what``)."""
    arrays = tuple(np.asarray(a, dtype=np.float64) for a in arrays)
    noise_px = np.asarray(noise_px, dtype=np.float64)
    F = len(arrays[0])
    if F < 1 or any(a.shape != (F, 4) for a in arrays) or noise_px.shape != (F,):
        raise InputError(
            f"{what}: errors, sigmas and variance ratios must be (F, 4) and the noise (F,), "
            f"got {', '.join(str(a.shape) for a in arrays)} and {noise_px.shape}"
        )
    if not all(np.all(np.isfinite(a)) for a in (*arrays, noise_px)):
        raise InputError(f"{what}: every input must be finite")
    return arrays + (noise_px,)


def fit_data_correlation(
    errors_px: np.ndarray,
    sigma_px: np.ndarray,
    variance_ratio: np.ndarray,
    noise_px: np.ndarray,
    noise_scale_px: float = NOISE_SCALE_PX,
) -> np.ndarray:
    """Per parameter, the rho in [0, 1] with which 68.27 % of F MAP estimates lie within their
    widened 1 sigma (``Uncertainty.posterior_scale``): errors_px (F, 4) against a reference
    independent of the frames' noise, sigma_px (F, 4) the MAP posterior's standard deviations,
    variance_ratio (F, 4) its variances over the prior's, noise_px (F,) the frames' 2D noise.
    0 where the posterior already covers 68.27 %, 1 where even rho = 1 does not (the widening
    grows with rho, so bisection finds it)."""
    errors_px, sigma_px, variance_ratio, noise_px = _map_inputs(
        "data correlation", errors_px, sigma_px, variance_ratio, noise_px=noise_px
    )
    e2 = errors_px**2

    def covered(rho: float, p: int) -> float:
        return np.mean(e2[:, p] <= _widened_variance(sigma_px, variance_ratio, noise_px, noise_scale_px, rho)[:, p])

    return np.array([_smallest_covering(lambda rho, p=p: covered(rho, p), 1.0) for p in range(4)])


def fit_data_bias(
    errors_px: np.ndarray,
    sigma_px: np.ndarray,
    variance_ratio: np.ndarray,
    noise_px: np.ndarray,
    network_sigma_px: np.ndarray,
    data_correlation: np.ndarray,
    noise_scale_px: float = NOISE_SCALE_PX,
) -> np.ndarray:
    """The data bias (4,): one b in [0, MAX_DATA_BIAS] for every parameter, the smallest with which
    95.45 % of F MAP estimates lie within twice sqrt(widened posterior variance + b^2 sigma_net^2)
    on every parameter at once (``Uncertainty.map_covariance``): the inputs as
    ``fit_data_correlation``'s, errors_px against the true K, network_sigma_px (F, 4) the network's
    standard deviations and data_correlation (4,) the fitted rho. 0 where the widened posterior
    already covers that. Fitted where the do-no-harm rules read K_cov (2 sigma, every parameter):
    a frame's data errors are heavy-tailed (a sheet bends or it does not), and a share that covers
    68 % of each parameter at 1 sigma left 19 % of the OIS-off frames outside (training/METHOD.md)."""
    errors_px, sigma_px, variance_ratio, network_sigma_px, noise_px = _map_inputs(
        "data bias", errors_px, sigma_px, variance_ratio, network_sigma_px, noise_px=noise_px
    )
    widened2 = _widened_variance(sigma_px, variance_ratio, noise_px, noise_scale_px, data_correlation)
    e2, net2 = errors_px**2 / 4.0, network_sigma_px**2  # within 2 sigma
    b = _smallest_covering(lambda b: np.mean(np.all(e2 <= widened2 + b * b * net2, 1)), MAX_DATA_BIAS, TWO_SIGMA)
    return np.full(4, b)


def coverage(estimate_px: np.ndarray, truth_px: np.ndarray, covariance: np.ndarray) -> dict:
    """Share of frames with |estimate - truth| <= 1 sigma, per parameter: (F, 4), (F, 4), (F, 4, 4)."""
    sigma = np.sqrt(np.einsum("fii->fi", covariance))
    inside = np.abs(np.asarray(estimate_px) - np.asarray(truth_px)) <= sigma
    return {name: float(inside[:, p].mean()) for p, name in enumerate(PARAMETERS)}
