from dataclasses import asdict, replace

import numpy as np
import pytest

from dimenet.runtime import __version__
from dimenet.runtime.errors import InputError
from dimenet.runtime.evaluation.metrics import reprojection_error_under_k
from dimenet.runtime.formats.dataset import read_dataset, write_dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.sim.profiles import PROFILES, get_profile
from dimenet.runtime.sim.simulator import focus_breathing_focal_px, ois_shift_px, simulate

# Paper Table 5 (test split): Avg(e_c), Avg(e*) in px; natural (LEGO) row for the Galaxy S8.
TABLE_5 = {"galaxy-s8": (3.44, 0.45), "iphone-12-pro": (2.36, 0.46), "ipad-mini-6": (1.61, 0.32)}
TABLE_5_NATURAL = (4.26, 3.45)
TABLE_1_SPLITS = {"galaxy-s8": (185, 47), "iphone-12-pro": (164, 42), "ipad-mini-6": (224, 57)}


def avg_errors(ds, cal, scene):
    """Avg(e_c) and Avg(e*) (px) over the test frames of ``scene``, K_c from the rig train frames."""
    m = ds.frames_in("test") & (ds.scene == scene)
    e_c = reprojection_error_under_k(ds.points_2d[m], ds.points_3d[m], ds.valid[m], cal.K_c)
    return float(e_c.mean()), float(cal.e_star[m].mean())


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("profile", sorted(TABLE_5))
def test_rig_test_split_reproduces_table_5_within_15_percent(simulated, profile, seed):
    e_c, e_star = avg_errors(*simulated(profile, seed), "rig")
    paper_e_c, paper_e_star = TABLE_5[profile]
    assert e_c == pytest.approx(paper_e_c, rel=0.15)
    assert e_star == pytest.approx(paper_e_star, rel=0.15)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_natural_frames_reproduce_table_5_lego_row_within_20_percent(simulated, seed):
    e_c, e_star = avg_errors(*simulated("galaxy-s8", seed), "natural")
    assert e_c == pytest.approx(TABLE_5_NATURAL[0], rel=0.20)
    assert e_star == pytest.approx(TABLE_5_NATURAL[1], rel=0.20)


@pytest.mark.parametrize("profile", sorted(TABLE_5))
def test_calibration_recovers_k_true_within_1px(simulated, profile):
    """The calibration's acceptance test: per-frame K* against the simulator's ground truth."""
    ds, cal = simulated(profile, 0)
    rig = ds.scene == "rig"
    error = np.abs(k_params(cal.K_star[rig]) - k_params(ds.K_true[rig])).mean(0)
    assert np.all(error <= 1.0), dict(zip(("fx", "fy", "cx", "cy"), error.round(3)))


def test_same_seed_same_data_other_seed_other_data(s8_dataset):
    again = simulate("galaxy-s8", seed=0, natural_frames=34)
    for key, value in s8_dataset.to_arrays().items():
        np.testing.assert_array_equal(again.to_arrays()[key], value)
    other = simulate("galaxy-s8", seed=1, natural_frames=34)
    assert not np.allclose(np.nan_to_num(other.points_2d), np.nan_to_num(s8_dataset.points_2d))
    assert not np.allclose(other.K_true, s8_dataset.K_true)


def test_rig_frames_do_not_depend_on_natural_frames(s8_dataset):
    rig_only = simulate("galaxy-s8", seed=0)
    rig = s8_dataset.select(s8_dataset.scene == "rig")
    np.testing.assert_array_equal(rig_only.points_2d, rig.points_2d)
    np.testing.assert_array_equal(rig_only.K_true, rig.K_true)


def test_write_read_round_trip_and_meta(s8_dataset, tmp_path):
    back = read_dataset(write_dataset(s8_dataset, tmp_path / "s8.npz"))
    for key, value in s8_dataset.to_arrays().items():
        np.testing.assert_array_equal(back.to_arrays()[key], value)
    meta = back.meta
    assert meta["generator"] == "dimenet.simulator" and meta["version"] == __version__
    assert meta["profile"] == "galaxy-s8" and meta["seed"] == 0 and meta["natural_frames"] == 34
    assert meta["units"] == {"2d": "px", "3d": "mm"}
    profile = get_profile("galaxy-s8")
    assert meta["device"]["shake_sigma_deg"] == profile.shake_sigma_deg
    assert set(meta["device"]) == set(asdict(profile))
    assert meta["rig"]["format"] == "dimenet-rig/1"


def test_layout_splits_scenes_and_masks(s8_dataset):
    ds = s8_dataset
    n_train, n_test = TABLE_1_SPLITS["galaxy-s8"]
    rig, natural = ds.scene == "rig", ds.scene == "natural"
    assert ds.n_frames == n_train + n_test + 34 and ds.n_points == 320
    assert (ds.frames_in("train") & rig).sum() == n_train and (ds.frames_in("test") & rig).sum() == n_test
    assert natural.sum() == 34 and np.all(ds.split[natural] == "test") and not ds.frames_in("val").any()
    assert ds.frame_id[7] == "galaxy-s8-0007" and len(set(ds.frame_id)) == ds.n_frames
    np.testing.assert_array_equal(ds.infer_mask[rig], ds.valid[rig])
    # Rig frames: whole boards of 80 corners, at least 2 of 4; absent points are NaN.
    counts = ds.valid[rig].sum(1)
    assert np.all(counts % 80 == 0) and counts.min() >= 160 and counts.max() == 320
    assert (counts < 320).any()  # the image border costs some frames a board
    assert np.isnan(ds.points_2d[~ds.valid]).all() and np.isnan(ds.points_3d[~ds.valid]).all()
    # Natural frames: 47 + 19 building features to infer from, plus the middle board for evaluation.
    np.testing.assert_array_equal(ds.infer_mask[natural].sum(1), 66)
    assert np.all(np.isin(ds.valid[natural].sum(1), [66, 146]))
    width, height = ds.image_size
    seen = ds.points_2d[ds.valid & ~natural[:, None]]
    assert np.all((seen >= 0) & (seen <= [width - 1, height - 1]))


@pytest.mark.parametrize("profile", sorted(TABLE_1_SPLITS))
def test_profile_splits_follow_table_1(profile):
    p = get_profile(profile)
    assert (p.n_train, p.n_test) == TABLE_1_SPLITS[profile] and p.image_size_px == (4032, 3024)


def test_ois_shift_is_f_tan_theta_clipped_at_the_stroke():
    f = 3000.0
    shift = ois_shift_px(np.array([0.5, -0.5, 3.0, -3.0]), f, 1.5)
    np.testing.assert_allclose(shift, f * np.tan(np.radians([0.5, -0.5, 1.5, -1.5])))


def test_dataset_principal_points_stay_within_the_stroke():
    profile = replace(get_profile("galaxy-s8"), shake_sigma_deg=5.0, n_train=20, n_test=20)
    ds = simulate(profile, seed=3)
    fx, _, cx, cy = k_params(ds.K_true).T
    limit = fx * np.tan(np.radians(profile.ois_stroke_deg))
    shift = np.abs(np.c_[cx, cy] - profile.centre_px)
    assert np.all(shift <= limit[:, None] + 1e-9)
    assert np.mean(np.isclose(shift, limit[:, None])) > 0.5  # a 5 deg shake saturates the actuator


def test_focus_breathing_follows_the_thin_lens():
    p = get_profile("galaxy-s8")
    near, far = focus_breathing_focal_px(p, 400.0), focus_breathing_focal_px(p, 700.0)
    assert p.focal_px < far < near
    assert near == pytest.approx(p.focal_px * 400.0 / (400.0 - p.focal_length_mm))
    with pytest.raises(InputError):
        focus_breathing_focal_px(p, 3.0)


def test_k_true_follows_focus_distance_and_ois_ignores_the_pose(s8_dataset, s8_calibration):
    rig = s8_dataset.scene == "rig"
    fx, fy, cx, cy = k_params(s8_dataset.K_true[rig]).T
    depth = s8_calibration.tvec[rig, 2]
    assert np.corrcoef(fx, depth)[0, 1] < -0.8  # focus breathing: nearer focus, longer focal length
    np.testing.assert_allclose(fy, fx * get_profile("galaxy-s8").pixel_aspect)
    for shift in (cx, cy):  # the OIS state is drawn independently of the camera pose
        for pose in np.c_[s8_calibration.rvec[rig], s8_calibration.tvec[rig]].T:
            assert abs(np.corrcoef(shift, pose)[0, 1]) < 0.25


def test_scale_matches_the_papers_5_45_px_per_mm(s8_dataset, s8_calibration):
    """Paper Sec. V-C: 'in our experimental setup 1 mm means about 5.45 pixels'."""
    rig = s8_dataset.scene == "rig"
    px_per_mm = s8_dataset.K_true[rig, 0, 0] / s8_calibration.tvec[rig, 2]
    assert px_per_mm.mean() == pytest.approx(5.45, rel=0.1)


def test_unknown_profile_and_bad_counts_raise_input_error():
    with pytest.raises(InputError, match="'pixel-9'.*galaxy-s8, ipad-mini-6, iphone-12-pro"):
        get_profile("pixel-9")
    with pytest.raises(InputError, match="pixel-9"):
        simulate("pixel-9")
    with pytest.raises(InputError, match="natural_frames"):
        simulate("galaxy-s8", natural_frames=-1)
    with pytest.raises(InputError, match="seed"):
        simulate("galaxy-s8", seed=1.5)
    assert set(PROFILES) == {"galaxy-s8", "iphone-12-pro", "ipad-mini-6"}


def test_planar_frames_infer_from_one_board_and_leave_the_other_frames_alone():
    plain = simulate("galaxy-s8", seed=5, natural_frames=2)
    ds = simulate("galaxy-s8", seed=5, natural_frames=2, planar_frames=4)
    np.testing.assert_array_equal(ds.points_2d[: plain.n_frames], plain.points_2d)
    planar = ds.scene == "planar"
    assert planar.sum() == 4 and np.all(ds.split[planar] == "test") and ds.meta["planar_frames"] == 4
    for f in np.flatnonzero(planar):
        X = ds.points_3d[f][ds.infer_mask[f]]
        assert np.linalg.svd(X - X.mean(0), compute_uv=False)[2] < 1e-6  # one board: coplanar
        assert ds.valid[f].sum() > ds.infer_mask[f].sum() >= 6


def test_label_noise_by_hand_and_as_the_dataset_records_it():
    from dimenet.runtime.sim.simulator import label_noise_px

    # f = 1000 px, Z = 1000 mm, a 1 mm error per axis: 1 px per axis on the axis (x = 0), sqrt(2) px at x = 1
    K = np.diag([1000.0, 1000.0, 1.0])
    assert label_noise_px(np.array([[0.0, 0.0, 1000.0]]), K, 2.0, 1.0) == pytest.approx(np.sqrt(5.0))
    assert label_noise_px(np.array([[1000.0, 0.0, 1000.0]]), K, 0.0, 1.0) == pytest.approx(np.sqrt(1.5))
    assert label_noise_px(np.array([[1000.0, 0.0, 1000.0]]), K, 0.7, 0.0) == pytest.approx(0.7)
    ds = simulate("galaxy-s8", seed=3, natural_frames=3)
    profile = get_profile("galaxy-s8")
    natural = ds.scene == "natural"
    np.testing.assert_array_equal(ds.label_noise_px[~natural], profile.corner_sigma_px)
    # the labels' noise and the 3D model's error as it projects: f sigma / Z px, Z about the camera's distances
    moved = profile.focal_px * profile.model_sigma_mm / np.array(profile.distance_mm)  # (near, far)
    low, high = np.hypot(profile.label_sigma_px, [moved[1] / 2.0, moved[0] * 2.0])
    assert np.all((ds.label_noise_px[natural] > low) & (ds.label_noise_px[natural] < high))
