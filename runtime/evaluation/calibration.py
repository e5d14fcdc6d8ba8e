"""Per-frame oracle calibration K* and the prior K_c a user gets from ordinary calibration.

K*: for each frame, the joint maximum-likelihood (K, pose) over all its valid points
(DLT start, then LM; ``geometry.least_squares.calibrate``). A rig view is non-planar, so one frame
suffices. e* is that fit's mean Euclidean reprojection error (px). A frame whose points lie in
one plane (a single board) does not give K: its K*, pose and e* are NaN and
``Calibration.reasons`` says why.

K_c: the mean of K* over the ``train`` frames, parameter by parameter (fx, fy, cx, cy).
This is the paper's "averaging a large number of K's under different OIS states"
(Sec. III-B); it is what a phone SDK hands an app. A train frame whose K* or e* lies far from
the others (``outliers``: a wrong point, a poisoned frame) stays out of the mean, so one bad
frame cannot move K_c; ``Calibration.outliers`` says which. When no train frame gives K (a set
of single-board views), K_c is their joint multi-view fit (``evaluation.multiview``).

Lens distortion: with a ``distortion`` model, one lens is fitted over the train frames (with each
rig frame's own K, ``geometry.lens_bundle``; with one K for single-board views,
``multiview.joint_fit``) and every frame is undistorted with it before its K*; a dataset that
carries its lens (``dist_coeffs`` about ``dist_K``) is undistorted with that. K* and K_c are
then the pinhole camera's, and ``Calibration`` carries the lens.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np

from dimenet.runtime.errors import CalibrationError, CameraError, DatasetError
from dimenet.runtime.evaluation.multiview import distortion_coefficients, joint_fit
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.dataset import LENS_KEYS, Dataset
from dimenet.runtime.formats.npz import read_npz
from dimenet.runtime.geometry import (
    calibrate,
    fit_lens_bundle,
    k_matrix,
    k_params,
    mean_reprojection_error,
    undistort_points,
)
from dimenet.runtime.rectify.user_camera import Camera, checked_camera, checked_dist_coeffs

CALIBRATION_KEYS = ("K_c", "K_star", "rvec", "tvec", "e_star")
# Optional keys: the lens (LENS_KEYS, both or neither) and why a frame has no K* ('' where it has one).
# A train frame is left out of K_c when a K* parameter or its e* lies this many robust standard
# deviations from the train frames' median (METHOD.md, "Runtime safety": no clean simulated
# frame comes near it; one wrong point moves a frame's K* by tens of px).
OUTLIER_SIGMAS = 8.0


@dataclass(frozen=True)
class Calibration:
    """K_c (3, 3) px; per frame K_star (F, 3, 3) px, pose rvec/tvec (F, 3) {W}->{C}, e_star (F,)
    px, NaN where ``reasons`` (F,) says why the frame gives no K (else None); outliers: the
    train frames left out of K_c; K_c_from: "mean K*" or "joint fit" (no train frame gave K*);
    the lens the K are under: dist_coeffs (n,) about dist_K (3, 3) px, or None."""

    K_c: np.ndarray
    K_star: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    e_star: np.ndarray
    outliers: tuple = ()
    reasons: tuple = ()
    K_c_from: str = "mean K*"
    dist_coeffs: Optional[np.ndarray] = None
    dist_K: Optional[np.ndarray] = None


def oracle_fit(points_2d, points_3d, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple]:
    """K*, rvec, tvec and e* (px) of each frame from all its valid points, NaN for the frames
    that give no K, and per frame the reason (None where it gives K)."""
    res = calibrate(points_2d, points_3d, valid, partial=True)
    e_star = np.full(len(points_2d), np.nan)
    ok = np.array([r is None for r in res.reasons], bool)
    if ok.any():
        e_star[ok] = mean_reprojection_error(
            points_2d[ok], points_3d[ok], valid[ok], res.K[ok], res.rvec[ok], res.tvec[ok]
        )
    return res.K, res.rvec, res.tvec, e_star, res.reasons


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


def _views(dataset: Dataset, frames: np.ndarray) -> list:
    return [
        (dataset.points_2d[b][dataset.valid[b]], dataset.points_3d[b][dataset.valid[b]]) for b in np.flatnonzero(frames)
    ]


def _pinhole(
    dataset: Dataset, distortion: str
) -> tuple[Dataset, Optional[np.ndarray], Optional[np.ndarray], Optional[np.ndarray]]:
    """The dataset's points in the pinhole camera, the lens (dist_coeffs, dist_K) they were
    undistorted with, and the joint fit's K when the lens came from one, else None.

    With a ``distortion`` model the lens is fitted over the train frames: where frames give K*
    (rig views), by the bundle adjustment of their own K and pose with one shared lens about the
    mean of their pinhole K* (``geometry.lens_bundle``: OIS moves K, the lens stays), the K*
    outliers left out; where none does (single-board views), by the joint fit of one K and the
    lens (``multiview.joint_fit``, Zhang's), which holds K fixed over the views (METHOD.md,
    "Lens distortion")."""
    if distortion == "none":
        if dataset.dist_coeffs is None:
            return dataset, None, None, None
        return dataset.undistorted(), dataset.dist_coeffs, dataset.dist_K, None
    n_coeffs = distortion_coefficients(distortion)
    train = dataset.select(dataset.frames_in("train"))
    K_star, rvec, tvec, e_star, _ = oracle_fit(train.points_2d, train.points_3d, train.valid)
    gives_k = np.all(np.isfinite(k_params(K_star)), axis=1)
    if gives_k.any():
        rows = np.flatnonzero(gives_k)
        rows = rows[~outliers(K_star[rows], e_star[rows])]
        if len(rows) == 0:
            raise CalibrationError("every train frame's K* is an outlier: no lens fit")
        points = tuple(a[rows] for a in (train.points_2d, train.points_3d, train.valid))
        lens = fit_lens_bundle(*points, K_star[rows], rvec[rows], tvec[rows], prior_k(K_star[rows]), np.zeros(n_coeffs))
        # Stated about the pinhole K*'s mean, which the lens biased, the lens is then refitted
        # about the mean of the bundle's own K: K_c (METHOD.md, "Lens distortion").
        K_lens = prior_k(lens.K)
        lens = fit_lens_bundle(*points, lens.K, lens.rvec, lens.tvec, K_lens, lens.dist_coeffs)
        return _undistorted(dataset, K_lens, lens.dist_coeffs), lens.dist_coeffs, K_lens, None
    views = _views(train, np.ones(train.n_frames, bool))
    lens = joint_fit(views, dataset.image_size, distortion, prior_k(K_star[gives_k]) if gives_k.any() else None)
    return _undistorted(dataset, lens.K, lens.dist_coeffs), lens.dist_coeffs, lens.K, lens.K


def _undistorted(dataset: Dataset, K_lens: np.ndarray, dist: np.ndarray) -> Dataset:
    points = np.where(dataset.valid[..., None], undistort_points(dataset.points_2d, K_lens, dist), np.nan)
    return replace(dataset, points_2d=points)


def calibrate_dataset(dataset: Dataset, distortion: str = "none") -> Calibration:
    """K* and e* for every frame (NaN with a reason where a frame gives none), K_c from the train
    frames (their joint fit where none gives K*). ``distortion``: a ``multiview`` model fitted
    jointly over the train frames ("none": the dataset's own lens, if it has one). Raises when
    there are no train frames, or nothing gives K_c."""
    train = dataset.frames_in("train")
    if not train.any():
        raise DatasetError("split: K_c comes from the train frames and this dataset has none")
    pinhole, dist_coeffs, dist_K, joint_K = _pinhole(dataset, distortion)
    K_star, rvec, tvec, e_star, reasons = oracle_fit(pinhole.points_2d, pinhole.points_3d, pinhole.valid)
    lens = {"dist_coeffs": dist_coeffs, "dist_K": dist_K, "reasons": reasons}
    rows = np.flatnonzero(train & np.array([r is None for r in reasons], bool))
    if len(rows) == 0:
        K_c = joint_K if joint_K is not None else joint_fit(_views(pinhole, train), dataset.image_size).K
        return Calibration(K_c, K_star, rvec, tvec, e_star, (), K_c_from="joint fit", **lens)
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
        **lens,
    )


def dataset_camera(dataset: Dataset) -> Camera:
    """The dataset's camera as ``dimenet calibrate`` finds it: K_c from its train split, its
    image size, and its lens if it carries one."""
    size = tuple(int(v) for v in dataset.image_size)
    train = dataset.frames_in("train")
    if not train.any():
        raise DatasetError("split: K_c comes from the train frames and this dataset has none")
    cal = calibrate_dataset(dataset.select(train))  # the other frames' K* are not needed
    return checked_camera(cal.K_c, size, "K_c calibrated on the dataset's train split", cal.dist_coeffs, cal.dist_K)


def write_calibration(cal: Calibration, path: str | Path) -> Path:
    """The calibration file: CALIBRATION_KEYS, the lens (LENS_KEYS) when there is one, and
    ``unobservable`` (F,) str, '' or why a frame gives no K*, when one does not."""
    arrays = {k: getattr(cal, k) for k in CALIBRATION_KEYS}
    if cal.dist_coeffs is not None:
        arrays.update(dist_coeffs=cal.dist_coeffs, dist_K=cal.dist_K)
    if any(r is not None for r in cal.reasons):
        arrays["unobservable"] = np.array([r or "" for r in cal.reasons])
    if cal.K_c_from != "mean K*":
        arrays["K_c_from"] = np.array(cal.K_c_from)
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
        lens = {}
        if any(k in arrays for k in LENS_KEYS):
            if not all(k in arrays for k in LENS_KEYS):
                raise DatasetError(f"{LENS_KEYS[0]} and {LENS_KEYS[1]}: give both or neither")
            dist_K = _calibration_array(arrays, "dist_K", (3, 3), "(3, 3)")
            try:
                dist = checked_dist_coeffs(arrays["dist_coeffs"], "dist_coeffs")
            except CameraError as exc:
                raise DatasetError(str(exc)) from None
            lens = {"dist_coeffs": dist, "dist_K": dist_K} if dist is not None else {}
        return Calibration(
            K_c=K_c,
            K_star=_calibration_array(arrays, "K_star", (F, 3, 3), "(F, 3, 3)"),
            rvec=_calibration_array(arrays, "rvec", (F, 3), "(F, 3)"),
            tvec=_calibration_array(arrays, "tvec", (F, 3), "(F, 3)"),
            e_star=_calibration_array(arrays, "e_star", (F,), "(F,)"),
            reasons=_reasons(arrays, F),
            K_c_from=_k_c_from(arrays),
            **lens,
        )
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None


def _reasons(arrays: dict, F: int) -> tuple:
    """The file's ``unobservable`` (F,) str as per-frame reasons (None where a frame gives K*)."""
    if "unobservable" not in arrays:
        return (None,) * F
    a = arrays["unobservable"]
    if a.dtype.kind != "U" or a.shape != (F,):
        raise DatasetError(f"unobservable: must be a str array of shape (F,), got {a.dtype} {a.shape}")
    return tuple(str(r) or None for r in a)


def _k_c_from(arrays: dict) -> str:
    """The file's ``K_c_from`` ("mean K*" when absent): how K_c was found."""
    if "K_c_from" not in arrays:
        return "mean K*"
    a = arrays["K_c_from"]
    if a.dtype.kind != "U" or a.shape != () or str(a) not in ("mean K*", "joint fit"):
        raise DatasetError(f"K_c_from: must be 'mean K*' or 'joint fit', got {a.dtype} {a.shape}")
    return str(a)
