"""K_c stays put when one train frame is poisoned: the frame is left out as an outlier."""

import dataclasses

import numpy as np
import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import CalibrationError, DatasetError
from dimenet.runtime.evaluation.calibration import calibrate_dataset, outliers
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.geometry import k_matrix, k_params


@pytest.mark.parametrize("bad_px", [(5000.0, 3500.0), (2500.0, 1800.0), (-4000.0, 6000.0)])
def test_one_poisoned_train_frame_moves_k_c_by_less_than_half_a_pixel(s8_dataset, s8_calibration, bad_px):
    train = np.flatnonzero(s8_dataset.frames_in("train"))
    b = train[3]
    p2 = s8_dataset.points_2d.copy()
    p2[b, np.flatnonzero(s8_dataset.valid[b])[5]] = bad_px
    cal = calibrate_dataset(dataclasses.replace(s8_dataset, points_2d=p2))
    assert cal.outliers == (b,)
    assert np.abs(k_params(cal.K_c) - k_params(s8_calibration.K_c)).max() < 0.5
    assert s8_calibration.outliers == ()  # the clean frames: none left out


def test_a_point_far_outside_the_image_is_no_dataset(s8_dataset):
    p2 = s8_dataset.points_2d.copy()
    b = np.flatnonzero(s8_dataset.frames_in("train"))[3]
    p2[b, np.flatnonzero(s8_dataset.valid[b])[5]] = (1e12, -1e12)
    with pytest.raises(DatasetError, match=f"frame {b} .* lies far outside the 4032x3024 px image"):
        dataclasses.replace(s8_dataset, points_2d=p2)


def test_outliers_hand_made():
    k = np.array([[3000.0, 3000.0, 2000.0, 1500.0]] * 9) + np.arange(9)[:, None] * [1.0, 1.0, 2.0, 2.0]
    e = np.full(9, 0.45) + np.arange(9) * 0.01
    assert not outliers(k_matrix(k), e).any()
    k[4, 2] += 400.0  # cx far from the others
    e[7] = 40.0  # a bad fit
    e[2] = 0.01  # a very good fit is no fault
    k[6, 0] = np.nan
    np.testing.assert_array_equal(np.flatnonzero(outliers(k_matrix(k), e)), [4, 6, 7])


def test_calibrate_names_the_left_out_frame_and_refuses_when_all_are_outliers(
    s8_dataset, tmp_path, capsys, monkeypatch
):
    train = np.flatnonzero(s8_dataset.frames_in("train"))
    p2 = s8_dataset.points_2d.copy()
    p2[train[0], np.flatnonzero(s8_dataset.valid[train[0]])[0]] = (5000.0, 3500.0)
    write_dataset(dataclasses.replace(s8_dataset, points_2d=p2), tmp_path / "poisoned.npz")
    assert main(["calibrate", str(tmp_path / "poisoned.npz"), "--out", str(tmp_path / "cal.npz")]) == 0
    out = capsys.readouterr().out
    assert "left out of K_c: " in out and f"K_c from {len(train) - 1} train frames" in out
    F = s8_dataset.n_frames
    nan_fit = (np.full((F, 3, 3), np.nan), np.zeros((F, 3)), np.zeros((F, 3)), np.full(F, np.nan), (None,) * F)
    monkeypatch.setattr("dimenet.runtime.evaluation.calibration.oracle_fit", lambda *a: nan_fit)
    with pytest.raises(CalibrationError, match="every train frame"):
        calibrate_dataset(s8_dataset)
