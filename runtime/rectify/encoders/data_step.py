"""The data step encoder (``FeatureSpec.data_step``, spec >= 1.7; not the paper's): what the frame's points say of K.

One Gauss-Newton step over (pose, K) from the C0 pose and K_c (``geometry.prior_step``) with a weak prior on K
(1 sigma STEP_PRIOR_REL * fx_c px per parameter): its Delta K (fx, fy, cx, cy) px clipped to +- STEP_CLIP_REL * fx_c
times the PMD's scale, then the log of each parameter's posterior sigma over the prior's (0 where the points do not
fix it, e.g. f and c on one plane). Read from the frame's monomial Gram (``geometry.monomial_gram``). Compiled: the
``size`` values after the grid in ``dimenet_frame_features``' output (runtime/native/dimenet_features.c).
"""

from __future__ import annotations

import math

import numpy as np

from dimenet.runtime.geometry import gram_normal_equations, prior_step

NAME = "data_step"
# The data step's inputs: Delta K (4) then log sigma ratios (4); its prior's 1 sigma over fx_c; the
# noise floor of its data weight (px).
STEP_SIZE = 8
STEP_PRIOR_REL = 0.1
# The step's Delta K is clipped to +- this x fx_c before scaling: OIS moves c by up to ~0.02 fx and a factory K_c
# is off by up to 0.03 f; a step past 0.05 fx_c is the prior's doing on points that fix no K (inputs of order 1).
STEP_CLIP_REL = 0.05
STEP_NOISE_FLOOR_PX = 0.1
# A posterior variance over the prior's below this reads as this (no log of 0 from a failed inverse).
STEP_VARIANCE_FLOOR = 1e-30


def size(spec) -> int:
    return STEP_SIZE if spec.data_step else 0


def encode(G: np.ndarray, n: int, K_c, spec) -> list:
    """The STEP_SIZE inputs of one frame of n points from its monomial Gram G (11, 11) under K_c (3, 3) px."""
    fx_c, fy_c = float(K_c[0, 0]), float(K_c[1, 1])
    prior_var = (STEP_PRIOR_REL * fx_c) ** 2
    JJ, Jr, rss = gram_normal_equations(G, fx_c, fy_c)
    step, cov, _ = prior_step(JJ, Jr, rss, 2 * n, np.eye(4) / prior_var, noise_floor_px=STEP_NOISE_FLOOR_PX)
    return _step_inputs(
        step[6:].tolist(), cov.diagonal()[6:].tolist(), prior_var, STEP_CLIP_REL * fx_c, spec.scale["dx"]
    )


def _step_inputs(step_px: list, variance_px2: list, prior_var: float, clip_px: float, pmd_scale: float) -> list:
    """The STEP_SIZE inputs from the step (4,) px and posterior variances (4,) px^2 of (fx, fy, cx, cy), its
    prior's variance (px^2) and clip (px): the clipped step times the PMD's scale, then the log sigma ratios
    (floats: 3 against 9 µs for numpy's calls on 4 values)."""
    shown = [min(max(d, -clip_px), clip_px) * pmd_scale for d in step_px]
    return shown + [0.5 * math.log(max(v / prior_var, STEP_VARIANCE_FLOOR)) for v in variance_px2]
