import json
from dataclasses import replace

import numpy as np
import pytest
from helpers import random_frames

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.formats.dataset import Dataset, read_dataset, validate_arrays, write_dataset
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.simulator import simulate


def make_arrays(frames=3, points=10, seed=0):
    rng = np.random.default_rng(seed)
    x, X, K, *_ = random_frames(rng, frames=frames, points=points)
    valid = np.ones((frames, points), bool)
    valid[0, -2:] = False
    x[0, -2:] = np.nan
    X[0, -2:] = np.nan
    return {
        "format": np.array("dimenet-dataset/1"),
        "image_size": np.array([4032, 3024], np.int64),
        "points_2d": x,
        "points_3d": X,
        "valid": valid,
        "infer_mask": valid.copy(),
        "split": np.array(["train", "test", "test"][:frames]),
        "scene": np.array(["rig"] * frames),
        "meta": np.array(json.dumps({"device": "unit-test"})),
        "K_true": K,
    }


def test_round_trip_preserves_every_array(tmp_path):
    ds = Dataset(**validate_arrays(make_arrays()))
    path = write_dataset(ds, tmp_path / "d.npz")
    back = read_dataset(path)
    for key, value in ds.to_arrays().items():
        np.testing.assert_array_equal(back.to_arrays()[key], value)
    assert back.meta == {"device": "unit-test"}


def test_optional_keys_may_be_absent_and_float32_is_widened(tmp_path):
    arrays = make_arrays()
    del arrays["K_true"]
    arrays["points_2d"] = arrays["points_2d"].astype(np.float32)
    arrays["split"] = np.array(["test", "test", "test"])  # no train, no val: still conforming
    np.savez(tmp_path / "d.npz", **arrays)
    ds = read_dataset(tmp_path / "d.npz")
    assert ds.K_true is None and ds.points_2d.dtype == np.float64


def _broken(key, value=None, drop=False):
    arrays = make_arrays()
    if drop:
        del arrays[key]
    else:
        arrays[key] = value
    return arrays


@pytest.mark.parametrize(
    "arrays, key, words",
    [
        (_broken("format", np.array("dimenet-dataset/2")), "format", "exactly"),
        (_broken("points_3d", np.zeros((3, 9, 3))), "points_3d", "shape"),
        (_broken("valid", drop=True), "valid", "missing"),
        (_broken("split", np.array(["train", "holdout", "test"])), "split", "unknown split"),
        (_broken("meta", np.array("[1, 2]")), "meta", "JSON object"),
        (_broken("meta", np.array("{not json")), "meta", "not valid JSON"),
        (_broken("image_size", np.array([4032.0, 3024.0])), "image_size", "integers"),
        (_broken("extra", np.zeros(3)), "extra", "unknown key"),
    ],
)
def test_non_conforming_arrays_are_rejected_by_name(arrays, key, words):
    with pytest.raises(DatasetError, match=f"{key}.*{words}"):
        validate_arrays(arrays)


def test_infer_mask_must_be_subset_of_valid():
    arrays = make_arrays()
    arrays["infer_mask"][0, -1] = True  # that point is not valid
    with pytest.raises(DatasetError, match="infer_mask.*subset"):
        validate_arrays(arrays)


def test_non_finite_valid_point_is_rejected():
    arrays = make_arrays()
    arrays["points_2d"][1, 3, 0] = np.inf
    with pytest.raises(DatasetError, match="non-finite.*frame 1"):
        validate_arrays(arrays)


def test_frame_with_too_few_points_is_rejected():
    arrays = make_arrays()
    arrays["valid"][2, 5:] = False
    arrays["infer_mask"][2, 5:] = False
    with pytest.raises(DatasetError, match="frame 2 has 5 valid points"):
        validate_arrays(arrays)


def test_object_arrays_are_refused_without_unpickling(tmp_path):
    arrays = make_arrays()
    arrays["meta"] = np.array([{"a": 1}], dtype=object)
    np.savez(tmp_path / "evil.npz", **arrays)
    with pytest.raises(DatasetError, match="object arrays"):
        read_dataset(tmp_path / "evil.npz")


def test_missing_and_garbage_files_are_named(tmp_path):
    with pytest.raises(DatasetError, match="no such dataset file"):
        read_dataset(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="junk.npz"):
        read_dataset(tmp_path / "junk.npz")


def test_failed_write_leaves_previous_file_intact(tmp_path, monkeypatch):
    ds = Dataset(**validate_arrays(make_arrays()))
    path = write_dataset(ds, tmp_path / "d.npz")
    before = path.read_bytes()

    def explode(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", explode)
    with pytest.raises(OSError):
        write_dataset(ds.select(np.array([True, False, False])), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["d.npz"]


def test_select_keeps_frames_in_order():
    ds = Dataset(**validate_arrays(make_arrays()))
    sub = ds.select(ds.frames_in("test"))
    assert sub.n_frames == 2 and list(sub.split) == ["test", "test"]
    np.testing.assert_array_equal(sub.points_3d, ds.points_3d[1:])


# --- optional keys: lens distortion (dist_coeffs about dist_K) and the platform's K per frame ---

DIST = np.array([0.08, -0.15, 0.0005, -0.0003, 0.05])


def with_extras(arrays=None):
    arrays = make_arrays() if arrays is None else arrays
    K = arrays["K_true"]
    arrays["K_platform"] = K + np.array([[0.7, 0, -0.4], [0, 0.7, 0.3], [0, 0, 0]])
    arrays["dist_coeffs"] = DIST.copy()
    arrays["dist_K"] = K[0].copy()
    return arrays


def test_round_trip_of_the_distortion_and_platform_keys(tmp_path):
    ds = Dataset(**validate_arrays(with_extras()))
    back = read_dataset(write_dataset(ds, tmp_path / "d.npz"))
    for key in ("K_platform", "dist_coeffs", "dist_K"):
        np.testing.assert_array_equal(getattr(back, key), getattr(ds, key))
        assert getattr(back, key).dtype == np.float64
    assert set(back.to_arrays()) == set(ds.to_arrays())


@pytest.mark.parametrize(
    "key, value, words",
    [
        ("dist_coeffs", np.zeros(6), "shape"),
        ("dist_coeffs", np.zeros((1, 5)), "shape"),
        ("dist_coeffs", np.array([0.1, np.nan, 0, 0]), "finite"),
        ("dist_coeffs", np.array([1e4, 0, 0, 0]), "magnitude"),
        ("dist_coeffs", np.array([1, 0, 0, 0], np.int64), "float"),
        ("dist_K", np.eye(3)[:2], "shape"),
        ("dist_K", np.array([[3000.0, 5.0, 2000], [0, 3000, 1500], [0, 0, 1]]), "pinhole"),
        ("K_platform", np.zeros((2, 3, 3)), "shape"),
        ("K_platform", "nan", "non-finite"),
        ("K_platform", "negative", "pinhole"),
    ],
)
def test_bad_distortion_and_platform_keys_are_rejected_by_name(key, value, words):
    arrays = with_extras()
    if isinstance(value, str):
        arrays[key] = arrays[key].copy()
        arrays[key][1, 0, 0] = np.nan if value == "nan" else -3000.0
    else:
        arrays[key] = value
    with pytest.raises(DatasetError, match=f"^{key}:.*{words}"):
        validate_arrays(arrays)


@pytest.mark.parametrize("drop", ["dist_coeffs", "dist_K"])
def test_distortion_keys_come_both_or_neither(drop):
    arrays = with_extras()
    del arrays[drop]
    kept = "dist_K" if drop == "dist_coeffs" else "dist_coeffs"
    with pytest.raises(DatasetError, match=f"^{kept}: needs {drop}"):
        validate_arrays(arrays)


def test_select_keeps_the_platform_k_of_the_frames_and_the_lens():
    ds = Dataset(**validate_arrays(with_extras()))
    sub = ds.select(ds.frames_in("test"))
    np.testing.assert_array_equal(sub.K_platform, ds.K_platform[1:])
    np.testing.assert_array_equal(sub.dist_coeffs, DIST)
    np.testing.assert_array_equal(sub.dist_K, ds.dist_K)


def test_undistorted_without_distortion_is_the_dataset_itself():
    ds = Dataset(**validate_arrays(make_arrays()))
    assert ds.undistorted() is ds


def test_undistorted_recovers_the_simulated_pinhole_points():
    """A distorted simulation whose views stay well inside the image (the rig at ~1 m), so the
    same seed sees the same points with and without the lens: undistorting gives the pinhole points."""
    profile = replace(get_profile("galaxy-s8"), distance_mm=(900.0, 1000.0), n_train=6, n_test=6)
    pinhole = simulate(profile, seed=4, natural_frames=2)
    distorted = simulate(profile, seed=4, natural_frames=2, dist_coeffs=DIST)
    np.testing.assert_array_equal(distorted.valid, pinhole.valid)
    m = pinhole.valid
    assert np.abs(distorted.points_2d[m] - pinhole.points_2d[m]).max() > 5.0  # the lens moves points by px
    back = distorted.undistorted()
    assert back.dist_coeffs is None and back.dist_K is None
    assert np.abs(back.points_2d[m] - pinhole.points_2d[m]).max() < 1e-6
    assert np.isnan(back.points_2d[~m]).all()
    np.testing.assert_array_equal(back.points_3d, distorted.points_3d)


def test_undistorted_names_a_lens_that_sends_points_out_of_the_image():
    arrays = with_extras()
    arrays["points_2d"][1, 0] = [3500.0, 2900.0]  # near the corner of the 4032x3024 image
    arrays["dist_K"] = np.array([[3000.0, 0, 2016], [0, 3010, 1512], [0, 0, 1]])
    arrays["dist_coeffs"] = np.array([3.298, -4.9, -1.35, -4.214, 1.526])  # no phone lens
    with pytest.raises(DatasetError, match="^undistorted: points_2d/points_3d: valid point 0 of frame 1"):
        Dataset(**validate_arrays(arrays)).undistorted()


def test_label_noise_round_trips_with_and_without_the_key(tmp_path):
    noise = np.array([0.5, 1.3, 2.6])
    ds = Dataset(**validate_arrays({**make_arrays(), "label_noise_px": noise}))
    back = read_dataset(write_dataset(ds, tmp_path / "noise.npz"))
    np.testing.assert_array_equal(back.label_noise_px, noise)
    np.testing.assert_array_equal(back.select(back.frames_in("test")).label_noise_px, noise[1:])
    without = read_dataset(write_dataset(Dataset(**validate_arrays(make_arrays())), tmp_path / "plain.npz"))
    assert without.label_noise_px is None and "label_noise_px" not in without.to_arrays()


@pytest.mark.parametrize(
    "value, words", [(np.ones(2), "shape"), (np.array([1.0, np.nan, 1.0]), "finite"), (-np.ones(3), ">= 0")]
)
def test_bad_label_noise_is_rejected_by_name(value, words):
    with pytest.raises(DatasetError, match=f"^label_noise_px:.*{words}"):
        validate_arrays({**make_arrays(), "label_noise_px": value})
