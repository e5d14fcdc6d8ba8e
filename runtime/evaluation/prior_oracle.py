"""The prior oracle (issue 50): what one frame allows a single-frame method with a Gaussian prior on K.

Per frame, the MAP fit of (K, pose) on the frame's inference points under the *true* population prior of K: the
mean and covariance of the K_true of the frames of its scene (its population), the data weighted by the frame's
true label noise (dataset key ``label_noise_px``, which the simulator writes). It is ``rectify.map_fit`` run to
convergence (ITERATIONS Gauss-Newton steps at most, from the PnP pose under the prior's mean) with the known noise
instead of the one the frame's residuals suggest. No single-frame method with a Gaussian prior on K can beat it on
average, so a method's rho over the prior oracle's (``metrics.ratio_interval``) says how much of what one frame
allows it reaches. It is not the ``oracle`` method, which is K* itself (the K fitted on all of the frame's valid
points, the board's corners included).

The population's covariance of (fx, fy, cx, cy) is singular as the simulator draws K (fy is fx times a fixed
pixel aspect; a camera without OIS has one principal point): JITTER_PX is added to each parameter's std so the
prior has a precision, a thousandth of a pixel, far below any error the metric can see.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dimenet.runtime.errors import DatasetError, InputError
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import k_matrix, k_params, solve_pnp_start
from dimenet.runtime.rectify.map_fit import map_fit

PRIOR_ORACLE = "prior-oracle"  # its name among the evaluation's methods
ITERATIONS = 20  # Gauss-Newton steps at most: the fit stops at the first that does not lower the cost
JITTER_PX = 1e-3  # added (as a variance, squared) to the population covariance's diagonal, px
MIN_FRAMES = 2  # a population's covariance needs this many frames


@dataclass(frozen=True)
class PriorOracle:
    """The prior oracle's K (F, 3, 3) px and posterior covariance K_cov (F, 4, 4) px^2 per frame; fallbacks: frames
    whose fit found no pose (they keep the prior's mean); priors: scene -> (mean (4,) px, covariance (4, 4) px^2)."""

    K: np.ndarray
    K_cov: np.ndarray
    fallbacks: int
    priors: dict


def missing_inputs(frames: Dataset) -> str | None:
    """Why ``frames`` cannot have a prior oracle (None when they can): it needs K_true and label_noise_px."""
    missing = [key for key in ("K_true", "label_noise_px") if getattr(frames, key) is None]
    if not missing:
        return None
    return (
        f"the prior oracle needs each frame's true K and label noise, and the dataset has no {' or '.join(missing)} "
        "(`dimenet simulate` writes both)"
    )


def population_prior(K_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The population prior of K from its frames' K_true (F, 3, 3) px, F >= MIN_FRAMES: mean (4,) px and
    covariance (4, 4) px^2 of (fx, fy, cx, cy), JITTER_PX^2 added to its diagonal (module docstring)."""
    k = k_params(np.asarray(K_true, dtype=np.float64))
    if len(k) < MIN_FRAMES:
        raise DatasetError(f"prior oracle: a population prior needs >= {MIN_FRAMES} frames with K_true, got {len(k)}")
    return k.mean(0), np.cov(k, rowvar=False) + np.eye(4) * JITTER_PX**2


def oracle_frame(points_2d, points_3d, k_mean, K_cov, noise_px: float):
    """One frame's MAP fit (``map_fit``) under the prior (k_mean (4,) px, K_cov (4, 4) px^2) with its data weighted
    by 1 / noise_px^2, from the PnP pose under the prior's mean: the MapFit; InputError when the points fix no pose."""
    rvec, tvec = solve_pnp_start(points_2d, points_3d, k_matrix(k_mean))
    return map_fit(points_2d, points_3d, k_mean, K_cov, rvec, tvec, iterations=ITERATIONS, noise_px=noise_px)


def prior_oracle(frames: Dataset) -> PriorOracle:
    """The prior oracle's K of every frame, each under the population prior of its scene's frames, from the frame's
    inference points. DatasetError when the frames lack K_true or label_noise_px, or a scene has too few frames."""
    why = missing_inputs(frames)
    if why is not None:
        raise DatasetError(f"methods: {PRIOR_ORACLE!r}: {why}")
    K = np.empty_like(frames.K_true)
    K_cov = np.empty((frames.n_frames, 4, 4))
    priors, fallbacks = {}, 0
    for scene in sorted(set(frames.scene.tolist())):
        members = np.flatnonzero(frames.scene == scene)
        try:
            k_mean, cov = priors[scene] = population_prior(frames.K_true[members])
        except DatasetError as exc:
            raise DatasetError(f"{exc} (scene {scene!r})") from None
        for f in members:
            m = frames.infer_mask[f]
            try:
                fit = oracle_frame(
                    frames.points_2d[f][m], frames.points_3d[f][m], k_mean, cov, frames.label_noise_px[f]
                )
                K[f], K_cov[f] = k_matrix(fit.k), fit.K_cov
            except InputError:
                K[f], K_cov[f] = k_matrix(k_mean), cov
                fallbacks += 1
    return PriorOracle(K=K, K_cov=K_cov, fallbacks=fallbacks, priors=priors)
