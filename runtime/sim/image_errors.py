"""How a real camera's detected points depart from the pinhole projection plus i.i.d. noise: the error structure
of real photos that a random-scene family draws per camera (models_spec/simulator.md, "Scene family").

- A residual lens: the phone's ISP removes most of the distortion, not all of it; a radial k1 about the nominal K
  that no K_c holds, peak U(+-RESIDUAL_LENS_PX) at the image's corner for a REFERENCE_WIDTH_PX wide camera (scaled
  with the width).
- Correlated corner bias: a board's detected corners share an offset (blur, lighting, the detector's own bias),
  one per board and frame, N(0, s) px per axis with s ~ U(0, CORNER_BIAS_PX) per camera, plus a linear field across
  the board of the same size edge to edge; clipped at BIAS_CLIP sigmas.
- JPEG noise: compression blurs and blocks the corners' surroundings, so the sub-pixel error grows heavy tails: a
  Student t (JPEG_DOF degrees of freedom) per corner and axis of scale U(0, JPEG_PX) per camera, clipped at
  JPEG_CLIP scales.
- ChArUco boards on CHARUCO_SHARE of the cameras: a board is detected in part (the corners inside the image, at
  least CHARUCO_MIN_CORNERS of them) and each corner is missed with probability U(0, CHARUCO_MISSING) per camera
  (a marker not decoded).

Pixels: OpenCV's (the centre of the top-left pixel at (0, 0)). The lens acts on the pinhole image, the detection
errors on the lens's image. None of it is in the dataset: K_true stays the pinhole K, the 3D points the rig's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from dimenet.runtime.geometry import distort_points
from dimenet.runtime.sim.profiles import DeviceProfile

REFERENCE_WIDTH_PX = 4032  # the paper's phones' width, where RESIDUAL_LENS_PX holds
RESIDUAL_LENS_PX = 3.0  # the residual lens's displacement at the image corner, U(+-this) x width / 4032 px
CORNER_BIAS_PX = 0.3  # a camera's corner-bias std, U(0, this) px
BIAS_CLIP = 4.0  # the bias field clipped at this many of its std per axis
JPEG_PX = 0.3  # a camera's JPEG error scale, U(0, this) px
JPEG_DOF = 3  # the JPEG error's Student t degrees of freedom (heavy tails)
JPEG_CLIP = 5.0  # the JPEG error clipped at this many scales
CHARUCO_SHARE = 0.3  # this share of the cameras photographs ChArUco boards
CHARUCO_MISSING = 0.2  # a ChArUco camera misses each corner with probability U(0, this)
CHARUCO_MIN_CORNERS = 6  # a ChArUco board counts as seen with at least this many corners


@dataclass(frozen=True)
class ImageErrors:
    """One camera's image errors (module doc): ``residual_k1`` the residual lens's radial coefficient about the
    nominal K (scale-free), ``bias_px`` and ``jpeg_px`` the corner bias's std and the JPEG error's scale (px),
    ``charuco_missing`` None for plain boards (seen whole or lost) or a ChArUco corner's miss probability, and
    ``seed`` the generator of the per-frame draws (apart from the simulator's, so poses and noise keep theirs)."""

    residual_k1: float
    bias_px: float
    jpeg_px: float
    charuco_missing: Optional[float]
    seed: int

    @property
    def min_board_corners(self) -> Optional[int]:
        """The fewest corners of a board that count as seeing it: None (all of them) for plain boards."""
        return None if self.charuco_missing is None else CHARUCO_MIN_CORNERS

    def reach_px(self, profile: DeviceProfile) -> float:
        """The most the errors move a point (px): what the border margin must grow by to keep points inside."""
        # 1.25: room for the principal point's offset from the image centre
        lens = abs(self.residual_k1) * _corner_radius(profile) ** 3 * profile.focal_px * 1.25
        return lens + BIAS_CLIP * self.bias_px + JPEG_CLIP * self.jpeg_px

    def margined(self, profile: DeviceProfile) -> DeviceProfile:
        """``profile`` with its border margin grown by ``reach_px``."""
        return replace(profile, border_margin_px=profile.border_margin_px + self.reach_px(profile))

    def lens(self, pinhole_px: np.ndarray, profile: DeviceProfile) -> np.ndarray:
        """(N, 2) the residual lens's image of pinhole pixels (N, 2) px."""
        if self.residual_k1 == 0.0:
            return pinhole_px
        return distort_points(pinhole_px, profile.nominal_K, np.array([self.residual_k1, 0.0, 0.0, 0.0]))

    def detection(self, image_px: np.ndarray, group: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(N, 2) px: the detected corners of one frame's seen points image_px (N, 2) px, group (N,) their board
        (>= 0; < 0 a labelled feature, left as it is): each board's bias field, then the JPEG error."""
        out = np.array(image_px, dtype=np.float64)
        for g in np.unique(group[group >= 0]):
            board = group == g
            pts = out[board]
            centre = pts.mean(0)
            half = max(float(np.max(np.abs(pts - centre))), 1.0)
            offset = rng.normal(0.0, self.bias_px, 2)
            gradient = rng.normal(0.0, self.bias_px / 2.0, (2, 2))
            field = offset + (pts - centre) / half @ gradient.T
            clip = BIAS_CLIP * self.bias_px
            out[board] += np.clip(field, -clip, clip)
            jpeg = rng.standard_t(JPEG_DOF, pts.shape) * self.jpeg_px
            out[board] += np.clip(jpeg, -JPEG_CLIP * self.jpeg_px, JPEG_CLIP * self.jpeg_px)
        return out

    def missed(self, seen: np.ndarray, group: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(N,) bool: which seen corners a ChArUco camera fails to detect (none for plain boards), a board left
        with fewer than CHARUCO_MIN_CORNERS losing all of them."""
        if self.charuco_missing is None:
            return np.zeros_like(seen)
        miss = seen & (group >= 0) & (rng.random(len(seen)) < self.charuco_missing)
        kept = seen & ~miss
        for g in np.unique(group[kept & (group >= 0)]):
            board = group == g
            if np.count_nonzero(kept[board]) < CHARUCO_MIN_CORNERS:
                miss |= board & seen
        return miss


def _corner_radius(profile: DeviceProfile) -> float:
    """The image corner's distance from the centre in focal lengths (scale-free)."""
    return math.hypot(*profile.image_size_px) / 2.0 / profile.focal_px


def draw_image_errors(profile: DeviceProfile, rng: np.random.Generator) -> ImageErrors:
    """One camera's ``ImageErrors`` drawn from ``rng`` (module doc), a pure function of its state."""
    peak_px = rng.uniform(-RESIDUAL_LENS_PX, RESIDUAL_LENS_PX) * profile.image_size_px[0] / REFERENCE_WIDTH_PX
    bias_px, jpeg_px = rng.uniform(0.0, CORNER_BIAS_PX), rng.uniform(0.0, JPEG_PX)
    charuco = rng.uniform() < CHARUCO_SHARE
    missing = rng.uniform(0.0, CHARUCO_MISSING)
    return ImageErrors(
        residual_k1=peak_px / (profile.focal_px * _corner_radius(profile) ** 3),
        bias_px=float(bias_px),
        jpeg_px=float(jpeg_px),
        charuco_missing=float(missing) if charuco else None,
        seed=int(rng.integers(2**32)),
    )
