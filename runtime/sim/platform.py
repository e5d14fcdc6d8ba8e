"""The phone SDK's per-frame K, simulated (dataset key ``K_platform``; models_spec/simulator.md,
"Platform K (simulated)").

The SDK is modelled as one that reads the lens's position sensors each frame (as Android's
Camera2 does: ``CaptureResult.STATISTICS_OIS_SAMPLES`` gives the optical centre's OIS shift in
px; ``LENS_FOCUS_DISTANCE`` the focus), on top of an exact factory calibration (the profile's
nominal K: focal length at infinity focus, optical centre with the OIS at rest):

- principal point: the OIS actuator's Hall sensors read the lens's (x, y) position, so the SDK
  knows the true shift (clipping at the stroke included) up to their position error;
- focal length: the autofocus actuator's Hall sensor reads the lens-to-sensor distance v, so
  the SDK knows f_px = v / pixel pitch (focus breathing) up to the same position error.

Each of the three lens axes errs by ``LENS_POSITION_SIGMA_UM`` (Gaussian, independent per axis
and frame), which in px is that length over the pixel pitch. fy follows fx by the calibrated
pixel aspect. The draws come from their own random stream, so asking for K_platform leaves
every other simulated array as it was.
"""

from __future__ import annotations

import numpy as np

from dimenet.runtime.sim.profiles import DeviceProfile

# Hall-sensor lens position error, 1 sigma per axis (um at the lens): "an accuracy of
# micrometers" in every axis (EP 3964800 A1, Hall sensor IC for a camera's triaxial lens
# position), and 1 % of the range for a trimmed Hall displacement sensor (Dupre et al., IEEE
# Sensors J. 2020), i.e. 1.1 um of the galaxy-s8's +-111 um lens stroke (4.25 mm * tan 1.5 deg).
LENS_POSITION_SIGMA_UM = 1.0
PLATFORM_STREAM = 1  # spawn key of the K_platform draws: SeedSequence(seed, spawn_key=(1,))
MODEL = "hall-readout/1"


def platform_rng(seed: int) -> np.random.Generator:
    """The generator of the K_platform draws of simulator seed ``seed``, independent of the
    simulator's own ``default_rng(seed)``."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(PLATFORM_STREAM,)))


def platform_sigma_px(profile: DeviceProfile) -> np.ndarray:
    """(4,) px the 1-sigma error of K_platform's (fx, fy, cx, cy): the lens position error over the pitch."""
    s = LENS_POSITION_SIGMA_UM / profile.pixel_pitch_um
    return np.array([s, s * profile.pixel_aspect, s, s])


def platform_matrices(K_true: np.ndarray, profile: DeviceProfile, rng: np.random.Generator) -> np.ndarray:
    """(F, 3, 3) px the SDK's K of frames whose true K is ``K_true`` (F, 3, 3) px: the lens
    position the Hall sensors read (v along the axis, the OIS x, y), each with its error."""
    s = LENS_POSITION_SIGMA_UM / profile.pixel_pitch_um
    error = rng.normal(0.0, s, (len(K_true), 3))  # px: focus (v / pitch), OIS x, OIS y
    K = np.array(K_true, dtype=np.float64)
    K[:, 0, 0] += error[:, 0]
    K[:, 1, 1] = K[:, 0, 0] * profile.pixel_aspect
    K[:, 0, 2] += error[:, 1]
    K[:, 1, 2] += error[:, 2]
    return K


def platform_meta(profile: DeviceProfile) -> dict:
    """The dataset meta's ``platform_k``: that K_platform is simulated, its model and stated 1 sigma."""
    return {
        "simulated": True,
        "model": MODEL,
        "description": "factory K (nominal, exact) + focus breathing and OIS shift read by the lens's Hall "
        "sensors, each lens axis with a Gaussian position error",
        "lens_position_sigma_um": LENS_POSITION_SIGMA_UM,
        "sigma_px": [float(v) for v in platform_sigma_px(profile)],
    }


# The SDK's K as users report it (issue 51): a second setting beside the Hall-sensor readout above. Android's
# LENS_INTRINSIC_CALIBRATION and ARKit's ARCamera.intrinsics are reported biased: f off by a per-camera bias, the
# principal point following the lens's true shift only in part and one frame late, the values quantised.
REPORTED_MODEL = "reported/1"
REPORTED_F_BIAS_REL = (0.005, 0.02)  # |f bias| / f, uniform, either sign, one per camera
REPORTED_C_GAIN = (0.7, 1.0)  # share of the true OIS shift the reported c follows, uniform, one per camera
REPORTED_LAG_FRAMES = 1  # the reported c is the previous frame's shift
REPORTED_QUANTUM_PX = 0.5  # the reported values are rounded to this


def reported_matrices(K_true: np.ndarray, K_rest: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """(F, 3, 3) px the SDK's K as users report it for frames in time order whose true K is ``K_true`` (F, 3, 3) px,
    K_rest (3, 3) px the factory K (OIS at rest): f = f_true (1 + bias), c = c_rest + gain (c_true - c_rest) of the
    frame REPORTED_LAG_FRAMES before (the first frames: c_rest), each rounded to REPORTED_QUANTUM_PX; and the
    drawn bias and gain."""
    bias = float(rng.uniform(*REPORTED_F_BIAS_REL) * rng.choice((-1.0, 1.0)))
    gain = float(rng.uniform(*REPORTED_C_GAIN))
    K_true = np.asarray(K_true, dtype=np.float64)
    rest = np.asarray(K_rest, dtype=np.float64)[:2, 2]
    shift = K_true[:, :2, 2] - rest
    lagged = np.zeros_like(shift)
    lagged[REPORTED_LAG_FRAMES:] = shift[: len(shift) - REPORTED_LAG_FRAMES]
    K = K_true.copy()
    K[:, 0, 0] *= 1.0 + bias
    K[:, 1, 1] *= 1.0 + bias
    K[:, :2, 2] = rest + gain * lagged
    K[:, :2, :] = np.round(K[:, :2, :] / REPORTED_QUANTUM_PX) * REPORTED_QUANTUM_PX
    return K, {
        "model": REPORTED_MODEL,
        "f_bias_rel": bias,
        "c_gain": gain,
        "lag_frames": REPORTED_LAG_FRAMES,
        "quantum_px": REPORTED_QUANTUM_PX,
    }
