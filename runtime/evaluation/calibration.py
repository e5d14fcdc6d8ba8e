"""Per-frame oracle calibration K* and the prior K_c a user gets from ordinary calibration.

K*: for each frame, the joint maximum-likelihood (K, pose) over all its valid points
(DLT start, then LM; see least_squares.calibrate). The rig is non-planar, so one frame
suffices. e* is that fit's mean Euclidean reprojection error (px).

K_c: the mean of K* over the ``train`` frames, parameter by parameter (fx, fy, cx, cy).
This is the paper's "averaging a large number of K's under different OIS states"
(Sec. III-B); it is what a phone SDK hands an app. A train frame whose K* or e* lies far from
the others (``outliers``: a wrong point, a poisoned frame) stays out of the mean, so one bad
frame cannot move K_c; ``Calibration.outliers`` says which.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimenet.runtime.errors import CalibrationError, DatasetError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.npz import read_npz
from dimenet.runtime.geometry import k_matrix, k_params, mean_reprojection_error
from dimenet.runtime.geometry.least_squares import calibrate
from dimenet.runtime.rectify.camera import Camera, checked_camera

CALIBRATION_KEYS = ("K_c", "K_star", "rvec", "tvec", "e_star")
# A train frame is left out of K_c when a K* parameter or its e* lies this many robust standard
# deviations from the train frames' median (METHOD.md, "Runtime safety": no clean simulated
# frame comes near it; one wrong point moves a frame's K* by tens of px).
OUTLIER_SIGMAS = 8.0


@dataclass(frozen=True)
class Calibration:
    """K_c (3, 3) px; per frame K_star (F, 3, 3) px, pose rvec/tvec (F, 3) {W}->{C}, e_star (F,) px."""

    K_c: np.ndarray
    K_star: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    e_star: np.ndarray
    outliers: tuple = ()


def oracle_fit(points_2d, points_3d, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """K*, rvec, tvec and e* (px) of each frame from all its valid points."""
    res = calibrate(points_2d, points_3d, valid)
    e_star = mean_reprojection_error(points_2d, points_3d, valid, res.K, res.rvec, res.tvec)
    return res.K, res.rvec, res.tvec, e_star


def prior_k(K_star: np.ndarray) -> np.ndarray:
    """K_c: the parameter-wise mean of the given per-frame K (F, 3, 3)."""
    if len(K_star) == 0:
        raise CalibrationError("K_c needs at least one frame")
    return k_matrix(k_params(K_star).mean(0))


def outliers(K_star: np.ndarray, e_star: np.ndarray) -> np.ndarray:
    """(F,) bool: frames whose K* (F, 3, 3) has a parameter, or whose e* (F,) px is above the
    median, more than OUTLIER_SIGMAS robust standard deviations (1.4826 MAD, floored at
    1e-6 of the median) from the frames' median; non-finite K* or e* too."""
    values = np.c_[k_params(K_star), e_star]
    finite = np.all(np.isfinite(values), axis=1)
    if not finite.any():
        return ~finite
    median = np.median(values[finite], axis=0)
    spread = 1.4826 * np.median(np.abs(values[finite] - median), axis=0)
    spread = np.maximum(spread, 1e-6 * np.abs(median) + 1e-12)
    z = (values - median) / spread
    z[:, 4] = np.maximum(z[:, 4], 0.0)  # a small e* is no fault
    with np.errstate(invalid="ignore"):
        return ~finite | np.any(np.abs(z) > OUTLIER_SIGMAS, axis=1)


def calibrate_dataset(dataset: Dataset) -> Calibration:
    """K* and e* for every frame, K_c from the train frames. Raises when there are none."""
    train = dataset.frames_in("train")
    if not train.any():
        raise DatasetError("split: K_c comes from the train frames and this dataset has none")
    K_star, rvec, tvec, e_star = oracle_fit(dataset.points_2d, dataset.points_3d, dataset.valid)
    rows = np.flatnonzero(train)
    out = outliers(K_star[rows], e_star[rows])
    if out.all():
        raise CalibrationError("every train frame's K* is an outlier or not finite: no K_c")
    return Calibration(
        K_c=prior_k(K_star[rows[~out]]),
        K_star=K_star,
        rvec=rvec,
        tvec=tvec,
        e_star=e_star,
        outliers=tuple(int(b) for b in rows[out]),
    )


def dataset_camera(dataset: Dataset) -> Camera:
    """The dataset's camera as ``dimenet calibrate`` finds it: K_c from its train split, and its
    image size."""
    size = tuple(int(v) for v in dataset.image_size)
    train = dataset.frames_in("train")
    if not train.any():
        raise DatasetError("split: K_c comes from the train frames and this dataset has none")
    K_c = calibrate_dataset(dataset.select(train)).K_c  # the other frames' K* are not needed
    return checked_camera(K_c, size, "K_c calibrated on the dataset's train split")


def write_calibration(cal: Calibration, path: str | Path) -> Path:
    arrays = {k: getattr(cal, k) for k in CALIBRATION_KEYS}
    return atomic_write(path, lambda f: np.savez(f, **arrays))


def _calibration_array(arrays: dict, key: str, shape: tuple, named: str) -> np.ndarray:
    """``arrays[key]`` as float64 if it is a float array of ``shape`` (``named``: as the spec writes it)."""
    a = arrays[key]
    if a.dtype.kind != "f" or a.shape != shape:
        raise DatasetError(f"{key}: must be a float array of shape {named}, got {a.dtype} {a.shape}")
    return a.astype(np.float64, copy=False)


def read_calibration(path: str | Path) -> Calibration:
    """Read a ``dimenet calibrate`` file (see models_spec/README.md). Raises DatasetError naming the file
    (never pickle-loads; a corrupt, truncated or oversized archive is refused before decoding)."""
    arrays = read_npz(path, DatasetError, "calibration file")
    missing = [k for k in CALIBRATION_KEYS if k not in arrays]
    if missing:
        raise DatasetError(f"{path}: not a dimenet calibration file (missing {missing[0]!r})")
    try:
        F = arrays["K_star"].shape[0] if arrays["K_star"].ndim == 3 else -1
        K_c = _calibration_array(arrays, "K_c", (3, 3), "(3, 3)")
        if not np.all(np.isfinite(K_c)):
            raise DatasetError("K_c: has non-finite entries")
        return Calibration(
            K_c=K_c,
            K_star=_calibration_array(arrays, "K_star", (F, 3, 3), "(F, 3, 3)"),
            rvec=_calibration_array(arrays, "rvec", (F, 3), "(F, 3)"),
            tvec=_calibration_array(arrays, "tvec", (F, 3), "(F, 3)"),
            e_star=_calibration_array(arrays, "e_star", (F,), "(F,)"),
        )
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None
