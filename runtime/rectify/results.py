"""What the rectifier returns: one frame's ``Rectification`` and B frames' ``BatchRectification``."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable, Optional

import numpy as np

# Every fallback's stable code and its kind: a refusal keeps K_c's own solution; a note (mode map
# only) says the MAP fit gave way and the network's K is returned. Codes are never reused or renamed.
REFUSAL, NOTE = "refusal", "note"
FALLBACK_CODES = {
    "no_k_inferred": REFUSAL,  # too few inference points, or no C0 pose on them
    "out_of_range": REFUSAL,  # e(K_c) beyond the model's range
    "implausible": REFUSAL,  # Delta K not finite, or K outside K_bounds
    "no_pose": REFUSAL,  # no PnP pose under the predicted K
    "behind_camera": REFUSAL,  # a point behind the camera at the pose under the predicted K
    "structure": REFUSAL,  # the residuals under K_c hold structure OIS does not make
    "worse_than_k_c": REFUSAL,  # the worse rule: e(K) above e(K_c)
    "mismatch": REFUSAL,  # the mismatch rule: the points do not fit this camera
    "not_significant": REFUSAL,  # the evidence rule: the frame's points do not show K's move beyond their noise
    "map_no_c0_pose": NOTE,  # no C0 pose under K_c to start the MAP fit
    "map_no_pose": NOTE,  # the points fix no MAP pose
    "map_no_step": NOTE,  # the MAP step did not lower the cost
    "map_implausible": NOTE,  # the MAP K outside K_bounds
    "map_behind_camera": NOTE,  # a point behind the camera at the MAP pose
}


class Fallback(str):
    """A fallback's message (a str, as ``fallback`` has always been) made with its stable ``code``
    (a key of FALLBACK_CODES) at the source, so no reader parses the text."""

    code: str

    def __new__(cls, code: str, message: str) -> Fallback:
        if code not in FALLBACK_CODES:
            raise ValueError(f"unknown fallback code {code!r}")
        self = super().__new__(cls, message)
        self.code = code
        return self

    def __getnewargs__(self) -> tuple:  # pickle and copy (a result sent to another process)
        return self.code, str(self)

    @property
    def refusal(self) -> bool:
        """K_c's own solution was returned (else a note: map gave way to the network's K)."""
        return FALLBACK_CODES[self.code] == REFUSAL


@dataclass(frozen=True)
class Rectification:
    """One frame. K (3, 3) px; rvec (3,) rad and tvec (3,) mm {W}->{C} under K; the mean Euclidean
    reprojection errors (px) over the given points under K and under K_c (each with its own
    pose); delta_k (4,) px the applied (dfx, dfy, dcx, dcy), 0 on fallback; fallback None or
    why K_c's solution (or in map mode, DIME-Net's) was returned; timings_us: microseconds per
    stage; K_cov (4, 4) px^2 the covariance of (fx, fy, cx, cy): the network's (mode dimenet)
    or the MAP posterior (mode map); None when K is K_c's or the model has no uncertainty;
    K_c (3, 3) px the prior used (``Rectifier.K_c``). ``covariance`` computes K_cov when first
    asked for: the hot path does not pay for it."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error_px: float
    reprojection_error_kc_px: float
    delta_k: np.ndarray
    fallback: Optional[str]
    timings_us: dict
    K_c: np.ndarray
    covariance: Optional[Callable[[], np.ndarray]] = field(default=None, repr=False, compare=False)

    @cached_property
    def K_cov(self) -> Optional[np.ndarray]:
        """(4, 4) px^2, computed on first access from ``covariance`` (None without one)."""
        return None if self.covariance is None else self.covariance()

    @property
    def fallback_code(self) -> Optional[str]:
        """``fallback``'s code (FALLBACK_CODES), None where there is none."""
        return None if self.fallback is None else self.fallback.code


@dataclass(frozen=True)
class BatchRectification:
    """B frames, as Rectification: K (B, 3, 3), rvec (B, 3), tvec (B, 3), errors (B,) px over
    each frame's valid points, delta_k (B, 4) px, fallback: one reason or None per frame;
    K_c (3, 3) px the prior used; K_cov (B, 4, 4) px^2, NaN for frames whose K is K_c's, or
    None without an uncertainty model."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error_px: np.ndarray
    reprojection_error_kc_px: np.ndarray
    delta_k: np.ndarray
    fallback: tuple
    K_c: np.ndarray
    K_cov: Optional[np.ndarray] = None

    @property
    def fallback_code(self) -> tuple:
        """Per frame ``fallback``'s code (FALLBACK_CODES) or None."""
        return tuple(None if f is None else f.code for f in self.fallback)


@dataclass(frozen=True)
class NetworkEstimate:
    """What the network says of one frame before any fallback rule (``Rectifier.network``, the
    full graph's outputs): delta_k (4,) (fx, fy, cx, cy) and K (3, 3) = K_c + Delta K in the
    camera's pixels; sigma (4,) px the standard deviations of Delta K (None: the model has no
    uncertainty model); features (1, D) float64, what the network read."""

    delta_k: np.ndarray
    K: np.ndarray
    sigma: Optional[np.ndarray]
    features: np.ndarray
