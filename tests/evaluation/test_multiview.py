"""Calibration beyond one view: single-board frames give no K* (NaN with a reason, never an
abort) and K_c comes from their joint multi-view fit; a lens distortion is fitted jointly over
the train frames and every frame's K* is the pinhole camera's; evaluate leaves out the frames
without K*, saying how many and why."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from dimenet.runtime.errors import CalibrationError
from dimenet.runtime.evaluation.calibration import calibrate_dataset, read_calibration, write_calibration
from dimenet.runtime.evaluation.methods import FLOOR, evaluate, format_table
from dimenet.runtime.evaluation.multiview import joint_fit
from dimenet.runtime.formats.dataset import FORMAT, Dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.sim.simulator import simulate

K_TRUE = np.array([[3100.0, 0.0, 2010.0], [0.0, 3090.0, 1520.0], [0.0, 0.0, 1.0]])
SIZE = (4032, 3024)
LENS = np.array([-0.11, 0.06, 0.0005, -0.0004, -0.02])
BOARD_MM = np.array([[25.0 * i, 25.0 * j, 0.0] for j in range(7) for i in range(10)])


def board_views(n_views: int, seed: int, dist=None, noise_px: float = 0.1) -> list:
    """One printed 10 x 7 board (25 mm) seen from n_views hand-held poses, 0.4-0.6 m away."""
    rng = np.random.default_rng(seed)
    views = []
    while len(views) < n_views:
        rvec = rng.uniform(-0.5, 0.5, 3)
        centre = BOARD_MM.mean(0)
        R = cv2.Rodrigues(rvec)[0]
        tvec = np.array([rng.uniform(-80, 80), rng.uniform(-60, 60), rng.uniform(400, 600)]) - R @ centre
        x = cv2.projectPoints(BOARD_MM, rvec, tvec, K_TRUE, dist)[0].reshape(-1, 2)
        if np.all((x > 0) & (x < np.array(SIZE) - 1)):
            views.append((x + rng.normal(0, noise_px, x.shape), BOARD_MM.copy()))
    return views


def board_dataset(views: list, split: str = "train") -> Dataset:
    F, P = len(views), len(BOARD_MM)
    return Dataset(
        image_size=np.array(SIZE),
        points_2d=np.stack([x for x, _ in views]),
        points_3d=np.stack([X for _, X in views]),
        valid=np.ones((F, P), bool),
        infer_mask=np.ones((F, P), bool),
        split=np.array([split] * F),
        scene=np.array(["board"] * F),
        meta={"format": FORMAT},
    )


def test_single_board_views_give_k_c_by_their_joint_fit_and_no_k_star(tmp_path):
    views = board_views(15, seed=1)
    cal = calibrate_dataset(board_dataset(views))
    assert cal.K_c_from == "joint fit"
    back = read_calibration(write_calibration(cal, tmp_path / "cal.npz"))
    assert back.K_c_from == "joint fit" and back.reasons == cal.reasons
    assert np.isnan(cal.K_star).all() and np.isnan(cal.e_star).all()
    assert all("coplanar" in r for r in cal.reasons)
    error = np.abs(k_params(cal.K_c) - k_params(K_TRUE))
    assert error[0] < 0.005 * 3100 and error[1] < 0.005 * 3090 and np.all(error[2:] < 0.005 * SIZE[0])
    # The same as OpenCV's own calibration of the same corners.
    objects = [X.astype(np.float32) for _, X in views]
    images = [x.astype(np.float32).reshape(-1, 1, 2) for x, _ in views]
    flags = cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    K_cv = cv2.calibrateCamera(objects, images, SIZE, None, None, flags=flags)[1]
    assert np.abs(k_params(cal.K_c) - k_params(K_cv)).max() < 0.5


def test_a_lens_is_fitted_jointly_and_recovered():
    views = board_views(20, seed=2, dist=LENS)
    fit = joint_fit(views, SIZE, "opencv5")
    assert fit.planar_views == 20 and fit.rms_px < 0.2
    assert np.abs(k_params(fit.K) - k_params(K_TRUE)).max() < 0.005 * 3100
    assert np.abs(fit.dist_coeffs[:2] - LENS[:2]).max() < 0.02
    pinhole = joint_fit(views, SIZE, "none")
    assert pinhole.dist_coeffs is None and pinhole.rms_px > 5 * fit.rms_px  # the lens is no pinhole
    with pytest.raises(CalibrationError, match="unknown model"):
        joint_fit(views, SIZE, "fisheye")


def test_a_distorted_rig_dataset_calibrates_under_its_lens(tmp_path):
    lens = simulate("galaxy-s8", seed=3, dist_coeffs=LENS[:4])
    truth = k_params(lens.K_true[lens.frames_in("train")]).mean(0)
    # The dataset's own lens (as the simulator states it): K_c and K* as the pinhole camera's.
    own = calibrate_dataset(lens)
    assert own.dist_coeffs is not None and np.abs(k_params(own.K_c) - truth).max() < 2.0
    assert np.nanmean(np.abs(k_params(own.K_star) - k_params(lens.K_true)), 0).max() < 1.5
    ignored = calibrate_dataset(lens.undistorted())
    assert own.e_star.mean() == pytest.approx(ignored.e_star.mean(), rel=1e-6)
    # Fitted (each frame's own K, one lens), the lens removes most of the distortion's error.
    fitted = calibrate_dataset(lens, distortion="opencv4")
    as_pinhole = calibrate_dataset(_without_lens(lens))
    assert fitted.e_star.mean() < 0.5 * as_pinhole.e_star.mean()
    path = write_calibration(fitted, tmp_path / "cal.npz")
    back = read_calibration(path)
    np.testing.assert_array_equal(back.dist_coeffs, fitted.dist_coeffs)
    np.testing.assert_array_equal(back.dist_K, fitted.dist_K)


def _without_lens(ds: Dataset) -> Dataset:
    """The distorted points, told to be pinhole ones (the lens dropped)."""
    return replace(ds, dist_coeffs=None, dist_K=None)


def test_frames_without_k_star_are_measured_against_their_homography_floor(s8_dataset, s8_calibration):
    test = s8_dataset.select(s8_dataset.frames_in("test") & (s8_dataset.scene == "rig"))
    boards = board_dataset(board_views(3, seed=4), split="test")
    P = test.n_points
    pad = lambda a, fill: np.concatenate([a, np.full(a.shape[:1] + (P - a.shape[1],) + a.shape[2:], fill)], 1)  # noqa: E731
    both = Dataset(
        image_size=test.image_size,
        points_2d=np.concatenate([test.points_2d, pad(boards.points_2d, np.nan)]),
        points_3d=np.concatenate([test.points_3d, pad(boards.points_3d, np.nan)]),
        valid=np.concatenate([test.valid, pad(boards.valid, False)]),
        infer_mask=np.concatenate([test.infer_mask, pad(boards.infer_mask, False)]),
        split=np.concatenate([test.split, boards.split]),
        scene=np.concatenate([test.scene, boards.scene]),
        meta=test.meta,
    )
    ev = evaluate(both, s8_calibration.K_c, lambda frames: np.broadcast_to(s8_calibration.K_c, (frames.n_frames, 3, 3)))
    assert ev.overall.n_frames == test.n_frames and ev.overall.reference == "K*"  # overall: the frames with K*
    plane = ev.scenes["board (one plane)"]
    assert plane.n_frames == 3 and plane.reference == FLOOR and 0 < plane.avg_e_star < plane.avg_e_c
    assert list(ev.floor_reasons.values()) == [3] and "coplanar" in next(iter(ev.floor_reasons))
    assert "3 frame(s) without K*" in format_table(ev) and ev.to_json()["against_floor"] == ev.floor_reasons
    only = evaluate(boards, s8_calibration.K_c)  # all of one plane: no longer refused
    assert only.overall.reference == FLOOR and only.overall.n_frames == 3
