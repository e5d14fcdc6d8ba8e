"""The network's uncertainty on Delta K: a 4x4 covariance (px^2) per frame.

Choice (models_spec/model-v1.md, "uncertainty"): not a second network head but a model of
the network's residuals, fitted after training on the early-stopping frames under the
training augmentation (fewer points, emptied cells, clustered noisy labels). It keeps the
network, and f(0) = 0 for the mean, untouched.

Per frame, four statistics of the inference points say how much the input can tell:
``n`` points, ``m`` occupied grid cells, ``d`` their mean PMD norm under K_c at the C0 pose
(px) and ``t`` the thickness of their 3D cloud (``thickness``: 0 on one plane, 1/3 for
an isotropic cloud). With z = [1, log n, log m, log max(d, D_FLOOR_PX), log max(t, T_FLOOR)],
each parameter's standard deviation is sigma_p = exp(coef_p . z) (px), and the covariance is
diag(sigma) C diag(sigma) with one correlation matrix C. Fitting: per parameter, the
Gaussian maximum-likelihood coef on the residuals K - K* (Newton, convex), then its
intercept rescaled so that 68.27 % of the fitting frames lie within 1 sigma, then C from
the standardised residuals. Models of spec 1.1 use the first three statistics only; a model
names the statistics it uses, and reads those columns of the (B, 4) statistics.

The network reads the same points as the MAP data term, so on noisy points their errors are
correlated, which the MAP posterior (independent prior and data) does not know. Spec 1.3 adds
per parameter a correlation rho_p, fitted on noisy fitting frames (``fit_data_correlation``),
by which mode map widens its posterior: for an estimate weighting prior and data as w = r and
1 - r (r the posterior over the prior variance), errors of correlation rho add
2 rho sqrt(r (1 - r)) times the posterior variance. The correlation comes from the noise, so it
is scaled by w(s) = s^2 / (s^2 + s0^2) with s the frame's 2D noise (px, the MAP fit's) and
s0 = NOISE_SCALE_PX: at corner-level noise (0.4 px) the two read independent information.

A frame's points also hold errors no noise model knows (a sheet that bends, boards placed off
their nominal pose): the data term reads them as K, and the network, which reads the frame's own
step, follows them too. A model whose residuals were fitted against the simulator's true K
(spec 1.10, ``data_bias``) adds per parameter b_p^2 times the network's covariance to the MAP
posterior: the share of what the network gets wrong that the frame's data gets wrong with it
(``fit_data_bias``; zeros: none, as models before spec 1.10).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from dimenet.runtime import native
from dimenet.runtime.errors import InputError
from dimenet.runtime.json_text import JsonProblem, is_number, numbers, required, shown

PARAMETERS = ("fx", "fy", "cx", "cy")
STATISTICS = ("log_points", "log_cells", "log_pmd", "log_thickness")
D_FLOOR_PX = 0.05  # PMD below this says nothing more: noise-free frames are not infinitely certain
T_FLOOR = 1e-6  # thickness of a plane to float rounding: log t stays finite on exactly planar points
# 2D noise (px) at which half of the prior-data correlation applies (how it was chosen:
# training/METHOD.md, "Calibration on fresh frames").
NOISE_SCALE_PX = 2.0
# The sigma range rule (``Uncertainty.from_dict``): every sigma within [SIGMA_MIN_PX, SIGMA_MAX_PX]
# over the box of plausible frame statistics: n in [1, MAX_POINTS] points, m in [1, the grid's
# cells] occupied cells, PMD d in [D_FLOOR_PX, MAX_PMD_PX] px, thickness t in [T_FLOOR, 1/3].
MAX_POINTS = 100_000
MAX_PMD_PX = 1_000.0
SIGMA_MIN_PX, SIGMA_MAX_PX = 1e-6, 1e6
# Largest data_bias b_p: a frame's data wrong by more than this many times the network's sigma
# would make MAP no better than the prior alone.
MAX_DATA_BIAS = 3.0


@dataclass(frozen=True)
class Uncertainty:
    """coef (4, 1 + S): per parameter (fx, fy, cx, cy), the weights of z = [1, the S statistics
    named in ``statistics``] (a subsequence of STATISTICS); correlation (4, 4): of the
    standardised residuals; data_correlation (4,): rho_p of the network's errors with the MAP
    data term's on noisy points, in [0, 1] (zeros: independent, as models before spec 1.3);
    noise_scale_px: the s0 (px) of the noise weight w(s); population_sigma_px (4,) px or None
    (before spec 1.6): the standard deviation of K* - K_c over the training frames, what is known
    of a frame's K without the network (the K_cov of a frame that keeps K_c); data_bias (4,):
    b_p in [0, MAX_DATA_BIAS], the MAP posterior's added b_p b_q times the network's covariance
    (zeros: none, as models before spec 1.10)."""

    coef: np.ndarray
    correlation: np.ndarray
    statistics: tuple = STATISTICS
    data_correlation: np.ndarray = field(default_factory=lambda: np.zeros(4))
    noise_scale_px: float = NOISE_SCALE_PX
    population_sigma_px: Optional[np.ndarray] = None
    data_bias: np.ndarray = field(default_factory=lambda: np.zeros(4))

    def __post_init__(self):
        if not set(self.statistics) <= set(STATISTICS) or len(set(self.statistics)) != len(self.statistics):
            raise ValueError(
                f"uncertainty: statistics must be distinct names among {list(STATISTICS)}, got {list(self.statistics)}"
            )
        if self.coef.shape != (4, 1 + len(self.statistics)) or self.correlation.shape != (4, 4):
            raise ValueError(
                f"uncertainty: coef must be 4x{1 + len(self.statistics)} and correlation 4x4, "
                f"got {self.coef.shape} and {self.correlation.shape}"
            )
        if not (np.all(np.isfinite(self.coef)) and np.all(np.isfinite(self.correlation))):
            raise ValueError("uncertainty: coef and correlation must be finite")
        if np.any(np.linalg.eigvalsh((self.correlation + self.correlation.T) / 2) <= 0):
            raise ValueError("uncertainty: the correlation matrix is not positive definite")
        rho = np.asarray(self.data_correlation, dtype=np.float64)
        if rho.shape != (4,) or not np.all((rho >= 0) & (rho <= 1)):
            raise ValueError(f"uncertainty: data_correlation must be 4 values in [0, 1], got {self.data_correlation!r}")
        if not (math.isfinite(self.noise_scale_px) and self.noise_scale_px > 0):
            raise ValueError(f"uncertainty: noise_scale_px must be a positive number, got {self.noise_scale_px!r}")
        object.__setattr__(self, "data_correlation", rho)
        bias = np.asarray(self.data_bias, dtype=np.float64)
        if bias.shape != (4,) or not np.all((bias >= 0) & (bias <= MAX_DATA_BIAS)):
            raise ValueError(
                f"uncertainty: data_bias must be 4 values in [0, {MAX_DATA_BIAS:g}], got {self.data_bias!r}"
            )
        object.__setattr__(self, "data_bias", bias)
        object.__setattr__(self, "_bias", np.outer(bias, bias) if bias.any() else None)  # per frame: one product
        if self.population_sigma_px is not None:
            pop = np.asarray(self.population_sigma_px, dtype=np.float64)
            if pop.shape != (4,) or not np.all((pop >= SIGMA_MIN_PX) & (pop <= SIGMA_MAX_PX)):
                raise ValueError(
                    f"uncertainty: population_sigma_px must be 4 values in [{SIGMA_MIN_PX:g}, {SIGMA_MAX_PX:g}] px, "
                    f"got {self.population_sigma_px!r}"
                )
            object.__setattr__(self, "population_sigma_px", pop)
        object.__setattr__(self, "_columns", [STATISTICS.index(name) for name in self.statistics])
        # per frame: the core's arguments, the reference's plain floats
        object.__setattr__(self, "_column_bytes", bytes(self._columns))
        c = tuple(np.ascontiguousarray(a, dtype=np.float64) for a in (self.coef, self.correlation))
        object.__setattr__(self, "_c", c)
        object.__setattr__(self, "_coef_rows", c[0].tolist())
        object.__setattr__(self, "_correlation_rows", c[1].tolist())
        object.__setattr__(self, "_rho", rho.tolist())  # plain floats for the per-frame widening

    @property
    def widens(self) -> bool:
        """Whether ``posterior_scale`` can differ from 1 (some rho_p > 0)."""
        return any(self._rho)

    def map_covariance(self, posterior: np.ndarray, network: np.ndarray, noise_px: float) -> np.ndarray:
        """The MAP K_cov (4, 4) px^2 from its independent-errors posterior and the network's
        covariance ``network`` (4, 4) px^2: widened by ``posterior_scale`` for the noise the two
        share, plus diag(b) network diag(b) for the errors of the frame's own data (``data_bias``)."""
        if self.widens:
            scale = np.array(self.posterior_scale((posterior.diagonal() / network.diagonal()).tolist(), noise_px))
            posterior = posterior * (scale[:, None] * scale)
        if self._bias is not None:
            posterior = posterior + network * self._bias
        return posterior

    def to_dict(self) -> dict:
        return (
            {
                "parameters": list(PARAMETERS),
                "statistics": ["1", *self.statistics],
                "coef": self.coef.tolist(),
                "correlation": self.correlation.tolist(),
                "data_correlation": self.data_correlation.tolist(),
                "noise_scale_px": self.noise_scale_px,
            }
            | ({} if self.population_sigma_px is None else {"population_sigma_px": self.population_sigma_px.tolist()})
            | ({"data_bias": self.data_bias.tolist()} if self.data_bias.any() else {})
        )

    @classmethod
    def from_dict(cls, d: Any, n_cells: int) -> Uncertainty:
        """From a spec's ``uncertainty`` object of a model with ``n_cells`` grid cells, every field
        checked (JsonProblem, a ValueError, names it), and the sigma range rule: each sigma within
        [SIGMA_MIN_PX, SIGMA_MAX_PX] over the box of plausible frame statistics."""
        if not isinstance(d, dict):
            raise JsonProblem(f"uncertainty must be an object, got {shown(d)}")
        if d.get("parameters", list(PARAMETERS)) != list(PARAMETERS):
            raise JsonProblem(f"uncertainty.parameters must be {list(PARAMETERS)}, got {shown(d['parameters'])}")
        names = d.get("statistics", ["1", *STATISTICS[:3]])  # 1.1 files: the first three
        if (
            not isinstance(names, list)
            or not names
            or names[0] != "1"
            or not all(isinstance(n, str) and n in STATISTICS for n in names[1:])
            or len(set(names[1:])) != len(names) - 1
        ):
            raise JsonProblem(
                f"uncertainty.statistics must be '1' then distinct names among {list(STATISTICS)}, got {shown(names)}"
            )
        statistics = tuple(names[1:])
        coef = numbers(required(d, "coef"), (4, len(names)), "uncertainty.coef")
        correlation = numbers(required(d, "correlation"), (4, 4), "uncertainty.correlation")
        if not (np.abs(correlation - correlation.T).max() <= 1e-9 and np.abs(np.diag(correlation) - 1).max() <= 1e-6):
            raise JsonProblem("uncertainty.correlation must be a symmetric matrix with a unit diagonal")
        rho = numbers(d.get("data_correlation", [0.0] * 4), (4,), "uncertainty.data_correlation")
        s0 = d.get("noise_scale_px", NOISE_SCALE_PX)
        if not (is_number(s0) and s0 > 0):
            raise JsonProblem(f"uncertainty.noise_scale_px must be a positive number, got {shown(s0)}")
        pop = d.get("population_sigma_px")
        pop = None if pop is None else numbers(pop, (4,), "uncertainty.population_sigma_px")
        bias = numbers(d.get("data_bias", [0.0] * 4), (4,), "uncertainty.data_bias")
        low, high = log_sigma_range(coef, statistics, n_cells)
        for p, name in enumerate(PARAMETERS):
            if not math.log(SIGMA_MIN_PX) <= low[p] <= high[p] <= math.log(SIGMA_MAX_PX):
                raise JsonProblem(
                    f"uncertainty.coef gives sigma_{name} from {_exp(low[p])} to {_exp(high[p])} px over "
                    f"plausible frames (n <= {MAX_POINTS} points, m <= {n_cells} cells, "
                    f"PMD {D_FLOOR_PX} to {MAX_PMD_PX:g} px, thickness {T_FLOOR:g} to 1/3), "
                    f"outside [{SIGMA_MIN_PX:g}, {SIGMA_MAX_PX:g}] px"
                )
        try:
            return cls(
                coef=coef,
                correlation=correlation,
                statistics=statistics,
                data_correlation=rho,
                noise_scale_px=float(s0),
                population_sigma_px=pop,
                data_bias=bias,
            )
        except ValueError as exc:
            raise JsonProblem(str(exc)) from None

    def posterior_scale(self, variance_ratio, noise_px: float) -> list:
        """Per parameter, the factor on the MAP posterior's standard deviation for the network's
        correlation with the data: sqrt(1 + 2 rho_p w(s) sqrt(r_p (1 - r_p))), with r_p
        (sequence of 4) the posterior over the prior variance and s = noise_px the frame's 2D
        noise. Plain floats: one frame's four numbers."""
        w = noise_px * noise_px / (noise_px * noise_px + self.noise_scale_px**2)
        return [
            math.sqrt(1.0 + 2.0 * rho * w * math.sqrt(max(r * (1.0 - r), 0.0))) if rho else 1.0
            for rho, r in zip(self._rho, variance_ratio)
        ]

    def population_covariance(self) -> Optional[np.ndarray]:
        """(4, 4) px^2 diag(population_sigma_px^2), or None without it."""
        return None if self.population_sigma_px is None else np.diag(self.population_sigma_px**2)

    def sigma(self, stats: np.ndarray) -> np.ndarray:
        """(B, 4) frame statistics (``frame_statistics``) -> (B, 4) standard deviations of
        (fx, fy, cx, cy), px."""
        stats = np.asarray(stats, dtype=np.float64)[:, self._columns]
        return np.exp(stats @ self.coef[:, 1:].T + self.coef[:, 0])

    def frame_covariance(self, n_points: int, occupied: int, mean_pmd_px: float, thickness_3d: float) -> np.ndarray:
        """``covariance`` of one frame from its four numbers (the runtime's single-frame path): in the compiled core
        where it is (``dimenet_network_covariance``, models_spec/BENCHMARKS.md has its us), else
        ``frame_covariance_reference``, the same numbers to the bit."""
        if native.core is None:
            return self.frame_covariance_reference(n_points, occupied, mean_pmd_px, thickness_3d)
        k_cov = np.empty((4, 4))
        native.core.network_covariance(
            n_points, occupied, mean_pmd_px, thickness_3d, D_FLOOR_PX, T_FLOOR, self._column_bytes, *self._c, k_cov
        )
        return k_cov

    def frame_covariance_reference(
        self, n_points: int, occupied: int, mean_pmd_px: float, thickness_3d: float
    ) -> np.ndarray:
        """``frame_covariance`` in plain floats, in a stated order the core follows: sigma_p = exp(coef_p0 +
        coef_p1 z_1 + ...) summed left to right (libm's log and exp, as ``math``'s), then (sigma_p sigma_q) C_pq.
        (The batch's ``covariance`` sums by a matrix product: the two agree to rounding.)"""
        all_z = (
            math.log(n_points),
            math.log(occupied),
            math.log(max(mean_pmd_px, D_FLOOR_PX)),
            math.log(max(thickness_3d, T_FLOOR)),
        )
        z = [all_z[c] for c in self._columns]
        sigma = []
        for row in self._coef_rows:
            acc = row[0]
            for w, v in zip(row[1:], z):
                acc = acc + w * v
            sigma.append(_float_exp(acc))
        return np.array(
            [[(s_p * s_q) * c for s_q, c in zip(sigma, row)] for s_p, row in zip(sigma, self._correlation_rows)]
        )

    def covariance(self, stats: np.ndarray) -> np.ndarray:
        """(B, 4) frame statistics -> (B, 4, 4) covariance of Delta K, px^2."""
        s = self.sigma(stats)
        return s[:, :, None] * self.correlation * s[:, None, :]


def thickness(trace: float, minors: float, det: float) -> float:
    """How far 3D points are from one plane, from the invariants of their covariance C
    (``geometry.covariance_invariants``): det(C) tr(C) / e2(C)^2, with e2 the sum of its 2x2
    principal minors. Scale free, in [0, 1/3]: 0 on one plane (or line), 1/3 for an isotropic
    cloud; for eigenvalues l1 >= l2 >= l3 about l3 (l1 + l2) / (l1 l2) when l3 is small, the
    plane's thickness squared over its extent."""
    # At most 1/3 in exact arithmetic; the clip bounds the rounding of (near-)collinear points.
    return min(max(det, 0.0) * trace / minors**2, 1 / 3) if minors > 0 else 0.0


def frame_statistics(n_points, occupied_cells, mean_pmd_px, thicknesses) -> np.ndarray:
    """(B, 4) [log n, log m, log max(d, D_FLOOR_PX), log max(t, T_FLOOR)] from (B,) counts,
    mean PMD norms (px) and thicknesses."""
    n = np.asarray(n_points, dtype=np.float64)
    m = np.asarray(occupied_cells, dtype=np.float64)
    if np.any(n < 1) or np.any(m < 1):
        raise InputError("uncertainty: a frame needs >= 1 inference point in >= 1 cell")
    d = np.maximum(np.asarray(mean_pmd_px, dtype=np.float64), D_FLOOR_PX)
    t = np.maximum(np.asarray(thicknesses, dtype=np.float64), T_FLOOR)
    return np.stack([np.log(n), np.log(m), np.log(d), np.log(t)], -1)


def occupied_cells(features: np.ndarray, n_channels: int) -> np.ndarray:
    """(B, D) grid features -> (B,) number of cells holding points (a zero cell is empty)."""
    return features.reshape(len(features), -1, n_channels).any(-1).sum(-1)  # count_nonzero(axis) is slower


def input_statistics(
    features: np.ndarray, n_points: np.ndarray, pmd_norms: np.ndarray, invariants_3d: tuple, n_channels: int
) -> np.ndarray:
    """(B, 4) statistics of B frames' inference points from what the caller has computed anyway:
    features (B, D) their grid features, n_points (B,) their count, pmd_norms (B,) px their mean
    PMD norm (``geometry.mean_residual_norms`` of the feature's PMD rows) and invariants_3d the
    ``geometry.covariance_invariants_batch`` (trace, minors, det, (B,) each) of their 3D points."""
    t = [thickness(*frame) for frame in zip(*(a.tolist() for a in invariants_3d))]
    return frame_statistics(n_points, occupied_cells(features, n_channels), pmd_norms, t)


def log_sigma_range(coef: np.ndarray, statistics: tuple, n_cells: int) -> tuple:
    """(4,) lowest and highest log sigma of each parameter over the box of plausible statistics
    (``MAX_POINTS``, ...): coef . z is linear, so its extremes are at the box's corners."""
    box = {
        "log_points": (0.0, math.log(MAX_POINTS)),
        "log_cells": (0.0, math.log(n_cells)),
        "log_pmd": (math.log(D_FLOOR_PX), math.log(MAX_PMD_PX)),
        "log_thickness": (math.log(T_FLOOR), math.log(1 / 3)),
    }
    low, high = coef[:, 0].copy(), coef[:, 0].copy()
    with np.errstate(over="ignore", invalid="ignore"):  # absurd coefficients give +-inf or NaN: refused
        for column, name in enumerate(statistics, start=1):
            ends = np.outer(coef[:, column], box[name])  # (4, 2)
            low += ends.min(1)
            high += ends.max(1)
    return low, high


def _float_exp(x: float) -> float:
    """libm's exp (``math.exp``'s, as the core's), inf where it overflows (math.exp raises there)."""
    try:
        return math.exp(x)
    except OverflowError:
        return math.inf


def _exp(x: float) -> str:
    """exp(x) for a message, also where it overflows a float."""
    return f"{math.exp(x):.3g}" if x < 700 else f"exp({x:.3g})"
