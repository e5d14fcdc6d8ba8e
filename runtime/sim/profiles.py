"""The simulated devices: ``DeviceProfile`` (one phone or tablet camera and how it was hand-held) and the
paper's three profiles (Table 1), by name (models_spec/simulator.md, "Parameters")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dimenet.runtime.errors import InputError


@dataclass(frozen=True)
class DeviceProfile:
    """One phone/tablet camera and how it was hand-held (units in the names)."""

    name: str
    focal_length_mm: float  # lens focal length at infinity focus
    pixel_pitch_um: float  # sensor pixel pitch
    shake_sigma_deg: float  # hand-shake angle, std per axis (tuned: Avg(e_c), Table 5)
    ois_stroke_deg: float  # largest angle the OIS actuator compensates, per axis
    corner_sigma_px: float  # checkerboard corner detection noise, std per axis (tuned: Avg(e*), Table 1)
    n_train: int  # rig frames in train (Table 1)
    n_test: int  # rig frames in test (Table 1)
    image_size_px: tuple[int, int] = (4032, 3024)  # width, height (Table 1)
    pixel_aspect: float = 1.0  # fy / fx (square pixels)
    centre_offset_px: tuple[float, float] = (0.0, 0.0)  # optical centre minus sensor centre, x and y
    af_error_rel: float = 0.03  # autofocus distance error, std as a fraction of the distance
    label_sigma_px: float = 4.9  # natural scene: hand-labelling noise of 2D features, std per axis (tuned: Table 5 N)
    model_sigma_mm: float = 0.5  # natural scene: CAD model/alignment error of 3D features, std per axis
    distance_mm: tuple[float, float] = (400.0, 700.0)  # camera to rig centre, uniform
    view_max_deg: float = 25.0  # viewing direction off the rig normal, uniform per axis (yaw, pitch)
    roll_max_deg: float = 10.0  # camera roll, uniform
    aim_jitter_mm: float = 50.0  # aim point off the rig centre in the rig plane, uniform per axis
    border_margin_px: float = 4.0  # a corner closer than this to the image border is not detected

    @property
    def focal_px(self) -> float:
        """Nominal focal length (px) at infinity focus."""
        return self.focal_length_mm / (self.pixel_pitch_um * 1e-3)

    @property
    def centre_px(self) -> np.ndarray:
        """(2,) optical centre (px) with the OIS at rest: sensor centre plus the fixed offset."""
        w, h = self.image_size_px
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0]) + np.asarray(self.centre_offset_px)

    @property
    def nominal_K(self) -> np.ndarray:
        """(3, 3) px the nominal K: infinity focus, OIS at rest (what lens distortion is stated about)."""
        (cx, cy), f = self.centre_px, self.focal_px
        return np.array([[f, 0.0, cx], [0.0, f * self.pixel_aspect, cy], [0.0, 0.0, 1.0]])


# The three profiles of the paper's Table 1, one a row (fields as DeviceProfile names them).
# fmt: off
_TABLE_1 = (
    # name             focal mm  pitch um  shake deg  OIS deg  corner px  train  test  centre offset px
    ("galaxy-s8",      4.25,     1.4,      1.4,       1.5,     0.36,      185,   47,   (9.0, -6.0)),
    ("iphone-12-pro",  4.2,      1.4,      0.77,      1.0,     0.37,      164,   42,   (-7.0, 5.0)),
    ("ipad-mini-6",    4.0,      1.3,      0.5,       0.8,     0.26,      224,   57,   (5.0, 8.0)),
)
# fmt: on
PROFILES = {row[0]: DeviceProfile(*row[:8], centre_offset_px=row[8]) for row in _TABLE_1}


def get_profile(name: str) -> DeviceProfile:
    """The named device profile; InputError naming it and the known ones when unknown."""
    if name not in PROFILES:
        raise InputError(f"unknown device profile {name!r}; known profiles: {', '.join(sorted(PROFILES))}")
    return PROFILES[name]
