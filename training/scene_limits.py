"""What the runtime's do-no-harm rules need from the training frames (training/METHOD.md,
"Residual structure"): the population spread of K* - K_c, the K_cov of a frame that keeps K_c,
and the largest residual structure the network was trained on, above which a frame keeps K_c."""

from __future__ import annotations

import numpy as np

from dimenet.runtime.geometry import MIN_STRUCTURE_POINTS, k_params, residual_structure, solve_pnp_start
from dimenet.runtime.rectify.checks import STRUCTURE_PX, STRUCTURE_RATIO
from dimenet.runtime.rectify.grid import Grid

from .config import TrainConfig
from .units import augment, clean, resynthesise

# Augmentation draws of the fitting frames the structure limit is measured on; the fewest inference
# points a frame it reads holds; the share of them the rule may send to K_c, and the margin on the
# structure at that share.
STRUCTURE_DRAWS = 10
STRUCTURE_LIMIT_POINTS = 100
STRUCTURE_SHARE = 0.001
STRUCTURE_MARGIN = 1.25


def population_sigma(units: list) -> np.ndarray:
    """(4,) px: the standard deviation of K* - K_c (fx, fy, cx, cy) over every train frame of
    ``units`` (model px): what is known of a frame's K without the network."""
    delta = np.concatenate([k_params(u.train_K_star) - k_params(u.camera.K) for u in units])
    return np.maximum(delta.std(0), 1e-3)


def structure_limit(units: list, config: TrainConfig, grid: Grid, rng: np.random.Generator) -> float:
    """The spec's ``residual_structure_px`` (model px): STRUCTURE_MARGIN times the structure
    (``geometry.residual_structure`` of the inference points under K_c at the C0 pose; 0 where its
    F is at most STRUCTURE_RATIO) that a share STRUCTURE_SHARE of the fitting frames of at least
    STRUCTURE_LIMIT_POINTS inference points exceeds, re-imaged clean (``clean``: what K and the pose
    make, without the build errors a simulated rig's sheets hold) under STRUCTURE_DRAWS draws of
    the training augmentation; at least STRUCTURE_PX. The rule keeps K_c on structure that neither
    OIS nor corner noise makes, so the limit is measured on frames of only those: a family whose
    rigs sag would otherwise raise it past every real bent sheet. Clustered, noisily labelled points
    fit the smooth field by chance, the fewer the more (up to 4 px at 40 points): read on them, the
    share's structure was the draw's luck (0.5 to 1.65 px across seeds; training/METHOD.md)."""
    amplitudes, fewest = [], max(MIN_STRUCTURE_POINTS, STRUCTURE_LIMIT_POINTS)
    for unit in units:
        for _ in range(STRUCTURE_DRAWS):
            frames = augment(resynthesise(unit.fit, clean(unit.truth), rng, config.resynthesis)[0], config, grid, rng)
            for b in range(frames.n_frames):
                m = frames.infer_mask[b]
                if m.sum() < fewest:
                    continue
                x, X = np.ascontiguousarray(frames.points_2d[b][m]), np.ascontiguousarray(frames.points_3d[b][m])
                s = residual_structure(x, X, unit.camera.K, *solve_pnp_start(x, X, unit.camera.K))
                amplitudes.append(s.amplitude_px if s.ratio > STRUCTURE_RATIO else 0.0)
    at_share = float(np.quantile(amplitudes, 1.0 - STRUCTURE_SHARE)) if amplitudes else 0.0
    return max(STRUCTURE_MARGIN * at_share, STRUCTURE_PX)
