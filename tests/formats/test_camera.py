"""camera.json files (models_spec/camera-files.md): the good file, every refused field, hostile files."""

from __future__ import annotations

import copy
import json
import math
import re

import numpy as np
import pytest

from dimenet.runtime import CameraError as ExportedCameraError
from dimenet.runtime.errors import CameraError, DimenetError
from dimenet.runtime.formats.camera_file import MAX_CAMERA_BYTES, read_camera
from dimenet.runtime.rectify.user_camera import Camera, checked_camera

K = [[3000.0, 0.0, 2015.5], [0.0, 3010.0, 1511.5], [0.0, 0.0, 1.0]]
GOOD = {"K": K, "image_size": [4032, 3024]}


def _write(tmp_path, content, name="camera.json"):
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content if isinstance(content, str) else json.dumps(content), encoding="utf-8")
    return path


def _with(path_value, value):
    """GOOD with the field at ``path_value`` (a key, or (key, row, col)) set to ``value``."""
    d = copy.deepcopy(GOOD)
    if isinstance(path_value, tuple):
        key, *index = path_value
        target = d[key]
        for i in index[:-1]:
            target = target[i]
        target[index[-1]] = value
    else:
        d[path_value] = value
    return d


def test_a_good_file_reads_as_float64_read_only_k_and_width_height(tmp_path):
    cam = read_camera(_write(tmp_path, {**GOOD, "dist_coeffs": [0.1, 0, 0, 0], "note": {"any": ["thing"]}}))
    assert isinstance(cam, Camera)
    assert cam.K.dtype == np.float64 and cam.K.shape == (3, 3)
    np.testing.assert_array_equal(cam.K, np.array(K))
    assert cam.image_size == (4032, 3024) and all(type(v) is int for v in cam.image_size)
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0
    # integers, integral floats for the size, a BOM, a str path
    path = tmp_path / "bom.json"
    path.write_bytes(
        b"\xef\xbb\xbf"
        + json.dumps({"K": [[3000, 0, 0], [0, 3000, 0], [0, 0, 1]], "image_size": [1000.0, 2000]}).encode()
    )
    cam = read_camera(str(path))
    assert cam.image_size == (1000, 2000) and cam.K[0, 0] == 3000.0


def test_the_error_is_a_typed_value_error_exported_by_the_runtime():
    assert issubclass(CameraError, DimenetError) and issubclass(CameraError, ValueError)
    assert ExportedCameraError is CameraError


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("K", [[1, 0, 0], [0, 1, 0]], r"K must be 3 x 3 numbers"),
        ("K", [[3000, 0, 2000, 0], [0, 3000, 1500, 0], [0, 0, 1, 0]], r"K must be 3 x 3 numbers"),
        ("K", [3000, 3000, 2000, 1500], r"K must be 3 x 3 numbers"),
        ("K", "eye(3)", r"K must be 3 x 3 numbers"),
        ("K", None, r"K must be 3 x 3 numbers"),
        (("K", 0, 0), "3000", r"K must hold finite numbers, got '3000'"),
        (("K", 0, 0), True, r"K must hold finite numbers, got True"),
        (("K", 0, 0), None, r"K must hold finite numbers"),
        (("K", 0, 0), [3000], r"K must hold finite numbers"),
        (("K", 1, 0), 0.5, r"K\[1\]\[0\] must be 0"),
        (("K", 2, 0), 1e-9, r"K\[2\]\[0\] must be 0"),
        (("K", 2, 1), -1.0, r"K\[2\]\[1\] must be 0"),
        (("K", 2, 2), 2.0, r"K\[2\]\[2\] must be 1"),
        (("K", 0, 1), 0.3, r"K\[0\]\[1\] \(skew\) must be 0: skew is not supported"),
        (("K", 0, 0), 0.0, r"K must have fx, fy > 0"),
        (("K", 1, 1), -3000.0, r"K must have fx, fy > 0"),
        (("K", 1, 1), 6001.0, r"K must have fy / fx in \[0.5, 2\]"),
        (("K", 1, 1), 1499.0, r"K must have fy / fx in \[0.5, 2\]"),
        (("K", 0, 2), 4032.0, r"K principal point .* outside the 4032x3024 px image"),
        (("K", 0, 2), -0.51, r"K principal point"),
        (("K", 1, 2), 3023.51, r"K principal point"),
        (("K", 1, 2), -3025, r"K principal point"),
        ("image_size", [4032], r"image_size must be 2 integers \(width, height\)"),
        ("image_size", [4032, 3024, 3], r"image_size must be 2 integers"),
        ("image_size", {"w": 4032, "h": 3024}, r"image_size must be 2 integers"),
        ("image_size", [4032.5, 3024], r"image_size must be an integer"),
        ("image_size", ["4032", 3024], r"image_size must be an integer"),
        ("image_size", [True, 3024], r"image_size must be an integer"),
        ("image_size", [0, 3024], r"image_size must be 1 to 100000"),
        ("image_size", [4032, 100001], r"image_size must be 1 to 100000"),
    ],
)
def test_every_bad_field_is_refused_naming_file_and_field(tmp_path, field, value, message):
    path = _write(tmp_path, _with(field, value))
    with pytest.raises(CameraError, match=rf"^{re.escape(str(path))}: {message}"):
        read_camera(path)


def test_the_principal_point_bounds_are_inclusive(tmp_path):
    for cx, cy in [(-0.5, -0.5), (4031.5, 3023.5)]:
        cam = read_camera(_write(tmp_path, _with("K", [[3000, 0, cx], [0, 3000, cy], [0, 0, 1]])))
        assert (cam.K[0, 2], cam.K[1, 2]) == (cx, cy)
    for ratio in (0.5, 2.0):
        read_camera(_write(tmp_path, _with(("K", 1, 1), 3000.0 * ratio)))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ({"image_size": [4032, 3024]}, r"no 'K'"),
        ({"K": K}, r"no 'image_size'"),
        ([GOOD], r"the camera file must be an object"),
        ("3000", r"the camera file must be an object"),
        ('{"K": [[1, 0, 0]', r"not valid JSON"),
        ("", r"not valid JSON"),
        ('{"K": 1, "K": 2, "image_size": [1, 1]}', r"key 'K' appears twice"),
        ("[" * 100 + "]" * 100, r"nested deeper than 32 levels"),
        ('{"K": ' + "[" * 100_000 + "]" * 100_000 + ', "image_size": [1, 1]}', r"larger than|longer than|nested"),
        ('{"K": [[NaN, 0, 0], [0, 1, 0], [0, 0, 1]], "image_size": [1, 1]}', r"K must hold finite numbers, got nan"),
        ('{"K": [[Infinity, 0, 0], [0, 1, 0], [0, 0, 1]], "image_size": [1, 1]}', r"K must hold finite numbers"),
        ('{"K": [[1e999, 0, 0], [0, 1, 0], [0, 0, 1]], "image_size": [1, 1]}', r"K must hold finite numbers"),
        ('{"K": [[' + "9" * 5000 + ', 0, 0], [0, 1, 0], [0, 0, 1]], "image_size": [1, 1]}', r"digits|integer"),
        ('{"K": [[3000, 0, 0], [0, 3000, 0], [0, 0, 1]], "image_size": [1e999, 1]}', r"image_size must be an integer"),
        ('{"K": [[3000, 0, 0], [0, 3000, 0], [0, 0, 1]], "image_size": [' + "9" * 400 + ", 1]}", r"image_size must"),
    ],
)
def test_malformed_and_hostile_json_is_refused_naming_the_file(tmp_path, content, message):
    path = _write(tmp_path, content)
    with pytest.raises(CameraError, match=rf"^{re.escape(str(path))}: .*{message}"):
        read_camera(path)


def test_missing_huge_and_binary_files_are_refused_naming_the_file(tmp_path):
    with pytest.raises(CameraError, match=r"missing\.json: cannot read the camera file"):
        read_camera(tmp_path / "missing.json")
    with pytest.raises(CameraError, match=rf"{tmp_path.name}: cannot read the camera file"):
        read_camera(tmp_path)  # a folder
    huge = _write(tmp_path, json.dumps(GOOD) + " " * MAX_CAMERA_BYTES, "huge.json")
    with pytest.raises(CameraError, match=rf"huge\.json: larger than {MAX_CAMERA_BYTES} bytes"):
        read_camera(huge)
    binary = _write(tmp_path, b'{"K": "\xff\xfe"}', "binary.json")
    with pytest.raises(CameraError, match=r"binary\.json:1: not UTF-8 text"):
        read_camera(binary)


def test_checked_camera_accepts_arrays_lists_and_numpy_scalars():
    cam = checked_camera(np.array(K, np.float32), np.array([4032, 3024]), "K_c")
    assert cam.K.dtype == np.float64 and cam.image_size == (4032, 3024)
    assert all(type(v) is int for v in cam.image_size)
    np.testing.assert_allclose(cam.K, np.array(K, np.float32))
    cam = checked_camera(K, (4032.0, np.int32(3024)))
    assert cam.image_size == (4032, 3024)
    source = np.array(K)
    cam = checked_camera(source, (4032, 3024))
    source[0, 0] = 1.0  # the Camera holds its own copy
    assert cam.K[0, 0] == 3000.0 and not cam.K.flags.writeable


@pytest.mark.parametrize(
    ("K_value", "size", "message"),
    [
        (np.eye(2), (10, 10), r"K must be a \(3, 3\) array, got shape \(2, 2\)"),
        (np.zeros((1, 3, 3)), (10, 10), r"K must be a \(3, 3\) array"),
        ([[1, 0, 0], [0, 1], [0, 0, 1]], (10, 10), r"K must be a \(3, 3\) array"),
        (np.eye(3, dtype=bool), (10, 10), r"K must be a \(3, 3\) array of real numbers, got dtype bool"),
        (np.eye(3, dtype=complex), (10, 10), r"K must be .* got dtype complex128"),
        ([["1", "0", "0"], ["0", "1", "0"], ["0", "0", "1"]], (10, 10), r"K must be .* got dtype <U1"),
        ([[1, None, 0], [0, 1, 0], [0, 0, 1]], (10, 10), r"K must be .* got dtype object"),
        ([[math.nan, 0, 0], [0, 1, 0], [0, 0, 1]], (10, 10), r"K must hold finite numbers"),
        ([[math.inf, 0, 0], [0, 1, 0], [0, 0, 1]], (10, 10), r"K must hold finite numbers"),
        ([[10, 0.5, 5], [0, 10, 5], [0, 0, 1]], (10, 10), r"K\[0\]\[1\] \(skew\) must be 0"),
        ([[10, 0, 5], [0, 10, 5], [0, 0, 2]], (10, 10), r"K\[2\]\[2\] must be 1"),
        ([[-10, 0, 5], [0, -10, 5], [0, 0, 1]], (10, 10), r"K must have fx, fy > 0"),
        ([[10, 0, 5], [0, 30, 5], [0, 0, 1]], (10, 10), r"K must have fy / fx"),
        ([[10, 0, 31], [0, 10, 5], [0, 0, 1]], (10, 10), r"K principal point \(31.0, 5.0\) px"),
        (K, "ab", r"image_size must be 2 integers"),
        (K, 4032, r"image_size must be 2 integers"),
        (K, None, r"image_size must be 2 integers"),
        (K, (4032,), r"image_size must be 2 integers"),
        (K, (4032, 3024, 1), r"image_size must be 2 integers"),
        (K, (4032.5, 3024), r"image_size must be 2 integers"),
        (K, (True, 3024), r"image_size must be 2 integers"),
        (K, (math.nan, 3024), r"image_size must be 2 integers"),
        (K, (math.inf, 3024), r"image_size must be 2 integers"),
        (K, ("4032", 3024), r"image_size must be 2 integers"),
        (K, (0, 3024), r"image_size must be 1 to 100000"),
        (K, (4032, 10**400), r"image_size must be 1 to 100000"),
    ],
)
def test_checked_camera_refuses_bad_values_naming_source_and_field(K_value, size, message):
    with pytest.raises(CameraError, match=rf"^Rectifier\.load\(K_c\): {message}"):
        checked_camera(K_value, size, "Rectifier.load(K_c)")


@pytest.mark.parametrize(
    ("size", "k"), [((1080, 1920), (1450.0, 959.5, 539.5)), ((3024, 4032), K[0][0:1] + [2015.5, 1511.5])]
)
def test_a_swapped_image_size_is_refused_naming_the_swap(tmp_path, size, k):
    f, cx, cy = k
    swapped = {"K": [[f, 0, cx], [0, f, cy], [0, 0, 1]], "image_size": list(size)}
    with pytest.raises(
        CameraError, match=rf"image_size {size[0]}x{size[1]} px looks swapped: .* centre of a {size[1]}x{size[0]}"
    ):
        read_camera(_write(tmp_path, swapped))
    assert read_camera(_write(tmp_path, {**swapped, "image_size": [size[1], size[0]]})).image_size == size[::-1]


def test_a_camera_made_directly_is_checked_as_a_file_is():
    with pytest.raises(CameraError, match=r"camera: K principal point .* outside the 4032x3024 px image"):
        Camera(np.array([[3000.0, 0, 4100.0], [0, 3000.0, 1511.5], [0, 0, 1]]), (4032, 3024))
    with pytest.raises(CameraError, match=r"camera: K must have fx, fy within 0\.1 to 50"):
        Camera(np.array([[4.25, 0, 211.5], [0, 4.25, 159.5], [0, 0, 1]]), (424, 320))
    with pytest.raises(CameraError, match=r"looks swapped"):
        Camera(np.array(K), (3024, 4032))
    cam = Camera([[3000, 0, 2015.5], [0, 3010, 1511.5], [0, 0, 1]], [4032, 3024])
    assert cam.K.dtype == np.float64 and not cam.K.flags.writeable and cam.image_size == (4032, 3024)
