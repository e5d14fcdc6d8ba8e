import json

import numpy as np
import pytest
from helpers import random_frames

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.formats.dataset import Dataset, read_dataset, validate_arrays, write_dataset


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
