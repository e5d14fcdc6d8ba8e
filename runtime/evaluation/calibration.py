"""Per-frame oracle calibration K* and the prior K_c a user gets from ordinary calibration.

K*: for each frame, the joint maximum-likelihood (K, pose) over all its valid points
(DLT start, then LM; see least_squares.calibrate). The rig is non-planar, so one frame
suffices. e* is that fit's mean Euclidean reprojection error (px).

K_c: the mean of K* over the ``train`` frames, parameter by parameter (fx, fy, cx, cy).
This is the paper's "averaging a large number of K's under different OIS states"
(Sec. III-B); it is what a phone SDK hands an app.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimenet.runtime.errors import CalibrationError, DatasetError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import k_matrix, k_params, mean_reprojection_error
from dimenet.runtime.geometry.least_squares import calibrate

CALIBRATION_KEYS = ("K_c", "K_star", "rvec", "tvec", "e_star")


@dataclass(frozen=True)
class Calibration:
    """K_c (3, 3) px; per frame K_star (F, 3, 3) px, pose rvec/tvec (F, 3) {W}->{C}, e_star (F,) px."""

    K_c: np.ndarray
    K_star: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    e_star: np.ndarray


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


def calibrate_dataset(dataset: Dataset) -> Calibration:
    """K* and e* for every frame, K_c from the train frames. Raises when there are none."""
    train = dataset.frames_in("train")
    if not train.any():
        raise DatasetError("split: K_c comes from the train frames and this dataset has none")
    K_star, rvec, tvec, e_star = oracle_fit(dataset.points_2d, dataset.points_3d, dataset.valid)
    return Calibration(K_c=prior_k(K_star[train]), K_star=K_star, rvec=rvec, tvec=tvec, e_star=e_star)


def write_calibration(cal: Calibration, path: str | Path) -> Path:
    arrays = {k: getattr(cal, k) for k in CALIBRATION_KEYS}
    return atomic_write(path, lambda f: np.savez(f, **arrays))


def read_calibration(path: str | Path) -> Calibration:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return Calibration(**{k: npz[k] for k in CALIBRATION_KEYS})
    except KeyError as exc:
        raise DatasetError(f"{path}: not a dimenet calibration file (missing {exc})") from None
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: not a readable calibration file ({exc})") from None
