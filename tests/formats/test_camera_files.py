"""Camera files in the ecosystem's formats (models_spec/camera-files.md): every format round-trips,
files written by the real tools (cv2.FileStorage, pycolmap) and laid out as the others write them
read as the same camera, COLMAP's 0.5 px shift, the choice of one camera, and hostile files."""

from __future__ import annotations

import base64
import io
import os
import re
import time

import cv2
import numpy as np
import pytest

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.camera_file import (
    FORMATS,
    MAX_CAMERA_BYTES,
    format_for_suffix,
    read_camera,
    write_camera,
)
from dimenet.runtime.formats.cameras import mrcal, opencv, values
from dimenet.runtime.rectify.user_camera import FOCAL_PER_SIDE, checked_camera

K = np.array([[3059.61436426714, 0.0, 2023.8328146289948], [0.0, 3059.622856598851, 1508.4933376453093], [0, 0, 1]])
SIZE = (4032, 3024)
D4 = [-0.2834081121702935, 0.07395907389290132, 0.00019359502856909603, 1.7618711454538528e-05]
D5 = [*D4, 0.012345678901234]
D8 = [*D5, 0.0011, -0.0021, 3.1e-4]
D12 = [*D8, 1.1e-4, -2.2e-4, 3.3e-5, -4.4e-6]
D14 = [*D12, 0.0012, -5.5e-4]
# The longest distortion each format holds.
HOLDS = {"opencv-yaml": 14, "opencv-xml": 14, "json": 14, "mrcal": 12, "ros": 8, "colmap": 8, "kalibr": 4}


def camera(dist=None, K_=K, size=SIZE):
    return checked_camera(K_, size, "test", dist)


def write(tmp_path, text, name="camera"):
    path = tmp_path / name
    path.write_bytes(text) if isinstance(text, bytes) else path.write_text(text, encoding="utf-8")
    return path


def assert_same(cam, K_, size, dist):
    np.testing.assert_allclose(cam.K, K_, rtol=0, atol=1e-9)
    assert cam.image_size == tuple(size) and all(type(v) is int for v in cam.image_size)
    if dist is None:
        assert cam.dist_coeffs is None
    else:
        np.testing.assert_array_equal(cam.dist_coeffs, dist)


# --- round trips --------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("dist", [None, D4, D5, D8, D12, D14], ids=lambda d: f"dist{0 if d is None else len(d)}")
def test_every_format_round_trips_what_it_holds_and_refuses_what_it_does_not(tmp_path, fmt, dist):
    path = tmp_path / f"cam-{fmt}"  # no suffix: the format is told from the content
    cam = camera(dist)
    if dist is not None and len(dist) > HOLDS[fmt]:
        with pytest.raises(CameraError, match=rf"^{re.escape(str(path))}: dist_coeffs of {len(dist)} coefficients"):
            write_camera(path, cam, fmt)
        assert not path.exists() and not list(tmp_path.iterdir())  # nothing written, no temp file
        return
    assert write_camera(path, cam, fmt) == path
    assert_same(read_camera(path), K, SIZE, dist)


@pytest.mark.parametrize("fmt", FORMATS)
def test_trailing_zero_coefficients_come_back_in_shortest_form(tmp_path, fmt):
    """k1 k2 p1 p2 with k3..k6 = 0 is the same lens: every format reads it back as 4 coefficients."""
    cam = camera([*D4, 0.0, 0.0, 0.0, 0.0])
    write_camera(tmp_path / "cam", cam, fmt)
    assert_same(read_camera(tmp_path / "cam"), K, SIZE, D4)
    write_camera(tmp_path / "cam", camera([0.0] * 5), fmt)
    assert read_camera(tmp_path / "cam").dist_coeffs is None


def test_the_suffix_names_a_format_only_where_it_is_unambiguous(tmp_path):
    assert format_for_suffix("a/cam.json") == "json" and format_for_suffix("CAM.XML") == "opencv-xml"
    assert format_for_suffix("cameras.txt") == "colmap" and format_for_suffix("m.cameramodel") == "mrcal"
    assert format_for_suffix("cam.yaml") is None and format_for_suffix("cam.yml") is None
    # ... and the reader never trusts it: an OpenCV YAML named .json, a COLMAP file named .yaml.
    write_camera(tmp_path / "cam.json", camera(D5), "opencv-yaml")
    assert_same(read_camera(tmp_path / "cam.json"), K, SIZE, D5)
    write_camera(tmp_path / "cam.yaml", camera(D4), "colmap")
    assert_same(read_camera(tmp_path / "cam.yaml"), K, SIZE, D4)


def test_writing_is_atomic_and_refuses_unknown_formats_and_a_lens_of_another_k(tmp_path):
    path = write(tmp_path, "old", "cam.txt")
    with pytest.raises(CameraError, match=r"cam\.txt: unknown camera format 'yaml'"):
        write_camera(path, camera(), "yaml")
    lens_K = K.copy()
    lens_K[0, 0] += 10.0
    moved = checked_camera(K, SIZE, "test", D4, lens_K)
    with pytest.raises(CameraError, match=r"cam\.txt: dist_coeffs are stated about another K"):
        write_camera(path, moved, "colmap")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["cam.txt"]


# --- COLMAP's pixel convention ------------------------------------------------------------------

COLMAP_FILE = """\
# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 3
1 SIMPLE_RADIAL 3072 2304 2559.6799999999998 1536 1152 -0.020499700000000001
2 PINHOLE 4032 3024 3059.61436426714 3059.622856598851 2024.3328146289948 1508.9933376453093
3 OPENCV_FISHEYE 1280 1024 500 500 640 512 0.10000000000000001 0.01 0 0
"""


def test_colmap_centres_pixels_half_a_pixel_off_and_is_shifted_both_ways(tmp_path):
    path = write(tmp_path, COLMAP_FILE, "cameras.txt")
    cam = read_camera(f"{path}#2")
    np.testing.assert_allclose(cam.K, K, rtol=0, atol=1e-9)  # cx, cy 0.5 px less than the file's
    # The same camera written by cv2.FileStorage (OpenCV's convention) reads as the same K.
    fs = cv2.FileStorage(str(tmp_path / "cv.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", SIZE[0])
    fs.write("image_height", SIZE[1])
    fs.write("camera_matrix", K)
    fs.release()
    opencv_cam = read_camera(tmp_path / "cv.yml")
    np.testing.assert_allclose(opencv_cam.K, cam.K, rtol=0, atol=1e-9)
    assert opencv_cam.image_size == cam.image_size
    # Written back, the file's principal point is 0.5 px more than K's, f unchanged.
    write_camera(tmp_path / "out.txt", opencv_cam, "colmap")
    line = (tmp_path / "out.txt").read_text().splitlines()[-1].split()
    assert line[:4] == ["1", "PINHOLE", "4032", "3024"]
    np.testing.assert_allclose([float(v) for v in line[4:]], [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
    # SIMPLE_RADIAL: one f, k as k1.
    cam1 = read_camera(path, name="1")
    np.testing.assert_allclose(cam1.K, [[2559.68, 0, 1535.5], [0, 2559.68, 1151.5], [0, 0, 1]], atol=1e-9)
    np.testing.assert_array_equal(cam1.dist_coeffs, [float("-0.020499700000000001"), 0, 0, 0])


# --- the real tools -----------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_files_cv2_filestorage_writes_are_read(tmp_path, suffix):
    """The calibration sample's keys, and the interactive calibration's (cameraMatrix, dist_coeffs
    as a row, cameraResolution as a sequence), and short keys with a float32 K and a size matrix."""
    path = str(tmp_path / f"sample{suffix}")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Tue Dec  2 10:00:00 2025")
    fs.write("nframes", 25)
    fs.write("image_width", SIZE[0])
    fs.write("image_height", SIZE[1])
    fs.writeComment("flags: +fix_aspectRatio")
    fs.write("flags", 2)
    fs.write("fisheye_model", 0)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array(D5).reshape(5, 1))
    fs.write("avg_reprojection_error", 0.39)
    fs.write("extrinsic_parameters", np.arange(150.0).reshape(25, 6))
    fs.write("image_points", np.zeros((25, 54, 2), np.float32).reshape(25, 54 * 2))
    fs.release()
    assert_same(read_camera(path), K, SIZE, D5)

    path = str(tmp_path / f"interactive{suffix}")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("calibrationDate", "Tue Dec  2 10:00:00 2025")
    fs.startWriteStruct("cameraResolution", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
    for side in SIZE:
        fs.write("", side)
    fs.endWriteStruct()
    fs.write("cameraMatrix", K)
    fs.write("cameraMatrix_std_dev", np.ones((4, 1)))
    fs.write("dist_coeffs", np.array([D8]))
    fs.release()
    assert_same(read_camera(path), K, SIZE, D8)

    path = str(tmp_path / f"short{suffix}")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("K", K.astype(np.float32))
    fs.write("D", np.array(D4))
    fs.write("imageSize", np.array([[SIZE[0]], [SIZE[1]]], np.float64))
    fs.release()
    assert_same(read_camera(path), K.astype(np.float32).astype(np.float64), SIZE, D4)


def test_files_dimenet_writes_are_what_cv2_filestorage_reads(tmp_path):
    for fmt in ("opencv-yaml", "opencv-xml"):
        path = write_camera(tmp_path / f"cam-{fmt}", camera(D12), fmt)
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), K)
        np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(), D12)
        assert (fs.getNode("image_width").real(), fs.getNode("image_height").real()) == SIZE
        fs.release()


COLMAP_MODELS = [
    ("SIMPLE_PINHOLE", [3000.5, 2016.25, 1512.75], [3000.5, 3000.5, 2015.75, 1512.25], None),
    ("PINHOLE", [3000.5, 3010.25, 2016.25, 1512.75], [3000.5, 3010.25, 2015.75, 1512.25], None),
    ("SIMPLE_RADIAL", [3000.5, 2016.25, 1512.75, -0.05], [3000.5, 3000.5, 2015.75, 1512.25], [-0.05, 0, 0, 0]),
    ("RADIAL", [3000.5, 2016.25, 1512.75, -0.05, 0.01], [3000.5, 3000.5, 2015.75, 1512.25], [-0.05, 0.01, 0, 0]),
    ("OPENCV", [3000.5, 3010.25, 2016.25, 1512.75, *D4], [3000.5, 3010.25, 2015.75, 1512.25], D4),
    ("FULL_OPENCV", [3000.5, 3010.25, 2016.25, 1512.75, *D8], [3000.5, 3010.25, 2015.75, 1512.25], D8),
]


def test_cameras_pycolmap_writes_are_read_and_project_as_pycolmap_does(tmp_path):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is not installed (the dev extra has it)")
    reconstruction = pycolmap.Reconstruction()
    for camera_id, (model, params, _, _) in enumerate(COLMAP_MODELS, 1):
        cam = pycolmap.Camera(model=model, width=SIZE[0], height=SIZE[1], params=params, camera_id=camera_id)
        reconstruction.add_camera(cam)
    reconstruction.write_text(str(tmp_path))
    path = tmp_path / "cameras.txt"
    with pytest.raises(CameraError, match=r"holds 6 cameras \(1, 2, 3, 4, 5, 6\): choose one as .*#NAME"):
        read_camera(path)
    X = np.array([[0.1, -0.05, 1.0], [-0.3, 0.2, 1.5], [0.4, 0.3, 0.9]])
    for camera_id, (_, _, k, dist) in enumerate(COLMAP_MODELS, 1):
        cam = read_camera(f"{path}#{camera_id}")
        assert_same(cam, np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1]]), SIZE, dist)
        # pycolmap's projection is OpenCV's (with this K and distortion) plus 0.5 px.
        ours = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)[0].reshape(-1, 2)
        np.testing.assert_allclose(reconstruction.cameras[camera_id].img_from_cam(X) - 0.5, ours, atol=1e-6)


def test_cameras_dimenet_writes_are_what_pycolmap_reads(tmp_path):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is not installed (the dev extra has it)")
    X = np.array([[0.1, -0.05, 1.0], [-0.3, 0.2, 1.5]])
    for dist, model in [(None, "PINHOLE"), (D4, "OPENCV"), (D5, "FULL_OPENCV"), (D8, "FULL_OPENCV")]:
        cam = camera(dist)
        write_camera(tmp_path / "cameras.txt", cam, "colmap")
        for other in ("images.txt", "points3D.txt"):
            (tmp_path / other).write_text("")
        theirs = pycolmap.Reconstruction(str(tmp_path)).cameras[1]
        assert theirs.model.name == model and (theirs.width, theirs.height) == SIZE
        ours = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)[0].reshape(-1, 2)
        np.testing.assert_allclose(theirs.img_from_cam(X) - 0.5, ours, atol=1e-6)


# --- files as the other tools write them --------------------------------------------------------

OPENCV_SAMPLE_YAML = """\
%YAML:1.0
---
calibration_time: "Tue 02 Dec 2025 10:00:00 AM UTC"
nframes: 13
image_width: 640
image_height: 480
board_width: 9
board_height: 6
square_size: 2.5000000000000000e+01
# flags:  +fix_aspectRatio +fix_principal_point +zero_tangent_dist
flags: 14
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 5.3591573396163199e+02, 0., 3.4228315473308373e+02, 0.,
       5.3591573396163199e+02, 2.3557082909788173e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -2.6637260909660682e-01, -3.8588898922304653e-02,
       1.7831947042852964e-03, -2.8122100441115472e-04,
       2.3839153080878486e-01 ]
avg_reprojection_error: 3.9259098975581364e-01
per_view_reprojection_errors: !!opencv-matrix
   rows: 2
   cols: 1
   dt: f
   data: [ 1.92965463e-01, 1.18204820e+00 ]
extrinsic_parameters: !!opencv-matrix
   rows: 2
   cols: 6
   dt: d
   data: [ 1.6, 0.1, -0.2, -36.0, -55.2, 280.0, 1.5, -0.1, 0.2, -40.0, -50.0, 300.0 ]
"""
OPENCV_SAMPLE = (
    [[535.91573396163199, 0, 342.28315473308373], [0, 535.91573396163199, 235.57082909788173], [0, 0, 1]],
    (640, 480),
    [-0.26637260909660682, -0.038588898922304653, 0.0017831947042852964, -0.00028122100441115472, 0.23839153080878486],
)

OPENCV_INTERACTIVE_XML = """\
<?xml version="1.0"?>
<opencv_storage>
<calibrationDate>"Tue Dec  2 10:00:00 2025"</calibrationDate>
<framesCount>25</framesCount>
<calibration_flags>"fix_principal_point"</calibration_flags>
<cameraResolution>
  1280 720</cameraResolution>
<cameraMatrix type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    1.0312500000000000e+03 0. 6.3950000000000000e+02 0.
    1.0318750000000000e+03 3.5950000000000000e+02 0. 0. 1.</data></cameraMatrix>
<cameraMatrix_std_dev type_id="opencv-matrix">
  <rows>4</rows>
  <cols>1</cols>
  <dt>d</dt>
  <data>
    1.5 1.5 0. 0.</data></cameraMatrix_std_dev>
<dist_coeffs type_id="opencv-matrix">
  <rows>1</rows>
  <cols>5</cols>
  <dt>d</dt>
  <data>
    1.2000000000000000e-01 -2.5000000000000000e-01 0. 0. 1.0000000000000001e-01</data></dist_coeffs>
<avg_reprojection_error>3.1e-01</avg_reprojection_error>
</opencv_storage>
"""

ROS_FILE = """\
image_width: 2448
image_height: 2050
camera_name: prosilica
camera_matrix:
  rows: 3
  cols: 3
  data: [4827.94, 0, 1223.5, 0, 4835.62, 1024.5, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.41527, 0.31874, -0.00197, 0.00071, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [4827.94, 0, 1223.5, 0, 0, 4835.62, 1024.5, 0, 0, 0, 1, 0]
"""

ROS_RATIONAL = """\
image_width: 960
image_height: 600
camera_name: narrow_stereo/left
camera_matrix:
  rows: 3
  cols: 3
  data: [420.1, 0, 479.1, 0, 420.2, 295.1, 0, 0, 1]
distortion_model: rational_polynomial
distortion_coefficients:
  rows: 1
  cols: 8
  data: [1.5, 0.4, 0.1, -9.2e-05, 0.1, 1.9, 0.9, 2e-05]
rectification_matrix:
  rows: 3
  cols: 3
  data: [0.99989, 0.01463, -0.00078, -0.01462, 0.99987, 0.00649, 0.00087, -0.00648, 0.99998]
projection_matrix:
  rows: 3
  cols: 4
  data: [600.0, 0.0, 480.0, -20.3, 0.0, 600.0, 300.0, 0.0, 0.0, 0.0, 1.0, 0.0]
"""

KALIBR_FILE = """\
cam0:
  T_cam_imu:
  - [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
  - [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768]
  - [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1:
  - [0.999997256477797, 0.002317135723275, 0.000343393120620, -0.110074137800478]
  - [-0.002312067192432, 0.999898048507103, -0.014090668452683, 0.000399121547014]
  - [-0.000376008102320, 0.014089835846691, 0.999900662638081, -0.000853702503357]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [0]
  camera_model: pinhole
  distortion_coeffs: [-0.28368365, 0.07451284, -0.00010473, -3e-05]
  distortion_model: radtan
  intrinsics: [457.587, 456.134, 379.999, 255.238]
  resolution: [752, 480]
  rostopic: /cam1/image_raw
"""


def mrcal_file(optimization_inputs: bytes, key: str = "lensmodel") -> str:
    """A model laid out as mrcal's cameramodel._write writes it (numbers as {:.10g})."""
    return f"""\
# generated on 2025-12-02 10:00:00 with   mrcal-calibrate-cameras --lensmodel LENSMODEL_OPENCV8 'frame*.jpg'
{{
    '{key}':  'LENSMODEL_OPENCV8',

    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....
    'intrinsics': [ 1761.181055, 1761.250444, 1965.706996, 1087.382471, 2.840813912, 0.9520587012, \
0.0003006091524, 3.385561305e-05, 0.1185103008, 3.076009219, 1.785734279, 0.4134296216,],

    'valid_intrinsics_region': [
    [ 10, 20 ],
    [ 3800, 20 ],
    [ 3800, 2100 ],
    [ 10, 2100 ],
    [ 10, 20 ],
],

    # extrinsics are rt_fromref
    'extrinsics': [ 0, 0, 0, 0, 0, 0,],

    'imagersize': [ 3840, 2160,],

    'icam_intrinsics': 0,

    # The optimization inputs contain all the data used to compute this model.
    'optimization_inputs': {optimization_inputs!r},

}}
"""


MRCAL = (
    [[1761.181055, 0, 1965.706996], [0, 1761.250444, 1087.382471], [0, 0, 1]],
    (3840, 2160),
    [2.840813912, 0.9520587012, 0.0003006091524, 3.385561305e-05, 0.1185103008, 3.076009219, 1.785734279, 0.4134296216],
)


def b85_npz(n: int) -> bytes:
    """Optimization inputs as mrcal stores them: a compressed npz, base-85."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, observations=np.random.default_rng(0).normal(size=n))
    return base64.b85encode(buffer.getvalue())


def test_files_laid_out_as_the_other_tools_write_them_are_read(tmp_path):
    assert_same(read_camera(write(tmp_path, OPENCV_SAMPLE_YAML)), *OPENCV_SAMPLE)
    assert_same(
        read_camera(write(tmp_path, OPENCV_INTERACTIVE_XML)),
        [[1031.25, 0, 639.5], [0, 1031.875, 359.5], [0, 0, 1]],
        (1280, 720),
        [0.12, -0.25, 0, 0, 0.1],
    )
    prosilica = [[4827.94, 0, 1223.5], [0, 4835.62, 1024.5], [0, 0, 1]]
    assert_same(read_camera(write(tmp_path, ROS_FILE)), prosilica, (2448, 2050), [-0.41527, 0.31874, -0.00197, 0.00071])
    # ROS assumes plumb_bob when distortion_model is absent (older files); the rational model's
    # 8 coefficients, an exponent PyYAML leaves a string ("2e-05") read as the number it is.
    old = ROS_FILE.replace("distortion_model: plumb_bob\n", "")
    assert_same(read_camera(write(tmp_path, old)), prosilica, (2448, 2050), [-0.41527, 0.31874, -0.00197, 0.00071])
    rational = read_camera(write(tmp_path, ROS_RATIONAL))
    assert_same(
        rational,
        [[420.1, 0, 479.1], [0, 420.2, 295.1], [0, 0, 1]],
        (960, 600),
        [1.5, 0.4, 0.1, -9.2e-05, 0.1, 1.9, 0.9, 2e-05],
    )
    kalibr = write(tmp_path, KALIBR_FILE, "camchain-imucam.yaml")
    cam1 = read_camera(f"{kalibr}#cam1")
    assert_same(
        cam1,
        [[457.587, 0, 379.999], [0, 456.134, 255.238], [0, 0, 1]],
        (752, 480),
        [-0.28368365, 0.07451284, -0.00010473, -3e-05],
    )
    cam0 = read_camera(kalibr, name="cam0")
    assert_same(
        cam0,
        [[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]],
        (752, 480),
        [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
    )
    # mrcal, with its optimization inputs (~200 KiB of base 85: no limit on a bytes literal), and
    # with the older key mrcal still reads.
    big = write(tmp_path, mrcal_file(b85_npz(30_000)), "camera-0.cameramodel")
    assert big.stat().st_size > 200_000
    assert_same(read_camera(big), *MRCAL)
    assert_same(read_camera(write(tmp_path, mrcal_file(b"", key="lens_model"))), *MRCAL)


def test_the_mrcal_file_dimenet_writes_has_what_mrcal_reads(tmp_path):
    """mrcal's reader: ast.literal_eval, then 'lensmodel', 'intrinsics', 'extrinsics' (6) and
    'imagersize' (mrcal itself is not on PyPI for this Python; its reader's checks, mirrored)."""
    import ast

    path = write_camera(tmp_path / "cam.cameramodel", camera(D8), "mrcal")
    d = ast.literal_eval(path.read_text())
    assert {"lensmodel", "intrinsics", "extrinsics", "imagersize"} <= set(d)
    assert d["lensmodel"] == "LENSMODEL_OPENCV8" and len(d["intrinsics"]) == 4 + 8 and len(d["extrinsics"]) == 6
    assert d["intrinsics"][:4] == [K[0, 0], K[1, 1], K[0, 2], K[1, 2]] and d["imagersize"] == list(SIZE)


# --- choosing one camera ------------------------------------------------------------------------


def test_a_multi_camera_file_needs_one_chosen_and_says_which_it_holds(tmp_path):
    kalibr = write(tmp_path, KALIBR_FILE, "camchain.yaml")
    with pytest.raises(
        CameraError, match=rf"^{re.escape(str(kalibr))}: holds 2 cameras \(cam0, cam1\): choose one as "
    ):
        read_camera(kalibr)
    with pytest.raises(CameraError, match=r"no camera 'cam2' \(it holds cam0, cam1\)"):
        read_camera(f"{kalibr}#cam2")
    colmap_path = write(tmp_path, COLMAP_FILE, "cameras.txt")
    with pytest.raises(CameraError, match=r"cameras\.txt: holds 3 cameras \(1, 2, 3\)"):
        read_camera(colmap_path)
    assert read_camera(colmap_path, name="02").image_size == SIZE  # an ID, leading zeros or not
    with pytest.raises(CameraError, match=r"cameras\.txt:6: MODEL OPENCV_FISHEYE is not supported"):
        read_camera(f"{colmap_path}#3")
    # One camera: no name needed; a name for a one-camera format is refused.
    one = write(tmp_path, KALIBR_FILE.split("cam1:")[0], "one.yaml")
    assert read_camera(one).image_size == (752, 480)
    ros = write(tmp_path, ROS_FILE, "ros.yaml")
    with pytest.raises(CameraError, match=r"ros\.yaml: a ros file holds one camera, there is none to choose as #left"):
        read_camera(f"{ros}#left")
    # A file whose own name has a '#' is read as it is.
    hashed = write(tmp_path, ROS_FILE, "ros#1.yaml")
    assert read_camera(hashed).image_size == (2448, 2050)


# --- hostile and wrong files --------------------------------------------------------------------

ROS_NO_D = ROS_FILE.split("distortion_model")[0]
CV_K = (
    "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
    "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
)

CV_DATA = "   data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n"
JSON_K = '{{"K": [[{f!r}, 0, 320], [0, {f!r}, 240], [0, 0, 1]], "image_size": [640, 480]}}'

HOSTILE = [
    ("not UTF-8", b"%YAML:1.0\n\xff\xfe\x00garbage", r":2: not UTF-8 text"),
    ("printable garbage", "\x01\x02 ::: }{ ][ ,,, \x7f", r": not valid YAML"),
    ("plain text", "hello camera\n", r": not a camera file of a known format"),
    ("empty", "", r": not valid JSON"),
    ("YAML list", "- 1\n- 2\n", r": not a camera file of a known format"),
    # OpenCV
    (
        "cv no K",
        "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n",
        r": no camera matrix \(camera_matrix, cameraMatrix, K\)",
    ),
    (
        "cv no size",
        CV_K.replace("image_width: 640\nimage_height: 480\n", "") + "   data: [1, 0, 2, 0, 1, 3, 0, 0, 1]\n",
        r": no image size",
    ),
    (
        "cv no height",
        CV_K.replace("image_height: 480\n", "") + "   data: [1, 0, 2, 0, 1, 3, 0, 0, 1]\n",
        r": no 'image_height'",
    ),
    ("cv NaN", CV_K + "   data: [.nan, 0, 320, 0, 500, 240, 0, 0, 1]\n", r": K must hold finite numbers"),
    (
        "cv 2x2",
        CV_K.replace("rows: 3\n   cols: 3", "rows: 2\n   cols: 2") + "   data: [1, 0, 0, 1]\n",
        r": camera_matrix must be 3 x 3 numbers, got 4",
    ),
    (
        "cv huge header",
        CV_K.replace("rows: 3", "rows: 30000").replace("cols: 3", "cols: 30000") + "   data: [1]\n",
        r": camera_matrix must be a small matrix, got 30000 x 30000",
    ),
    ("cv short data", CV_K + "   data: [1, 0, 2]\n", r": camera_matrix is not a valid opencv-matrix"),
    (
        "cv string width",
        CV_K.replace("640", '"wide"') + "   data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n",
        r": image_width must be a number",
    ),
    (
        "cv fisheye",
        CV_K + "   data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\nfisheye_model: 1\n",
        r": fisheye_model: a fisheye calibration is not supported",
    ),
    (
        "cv omni",
        CV_K + "   data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\ncalibrationModel: omni\n",
        r": calibrationModel 'omni' is not supported",
    ),
    ("cv skew", CV_K + "   data: [500, 3, 320, 0, 500, 240, 0, 0, 1]\n", r": K\[0\]\[1\] \(skew\) must be 0"),
    ("cv unterminated", CV_K + "   data: [500, 0, 320,\n", r": not a valid OpenCV YAML file"),
    (
        "cv deep",
        "%YAML:1.0\n---\na: " + "[" * 100_000 + "]" * 100_000 + "\n",
        r": 100005 nesting characters, more than 1000",
    ),
    ("cv deep keys", "%YAML:1.0\n---\n" + "a: " * 60_000 + "1\n", r": 60004 nesting characters, more than 1000"),
    (
        "xml deep",
        '<?xml version="1.0"?>\n<opencv_storage>' + "<a>" * 50_000 + "</a>" * 50_000 + "</opencv_storage>\n",
        r": 100003 nesting characters, more than 1000",
    ),
    (
        "xml broken",
        '<?xml version="1.0"?>\n<opencv_storage><camera_matrix type_id="opencv-matrix"><rows>3',
        r": not a valid OpenCV XML file",
    ),
    # ROS
    ("ros no width", ROS_FILE.replace("image_width: 2448\n", ""), r": no 'image_width'"),
    (
        "ros K a list",
        "image_width: 1\nimage_height: 1\ncamera_matrix: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n",
        r": camera_matrix must be a mapping",
    ),
    ("ros K strings", ROS_NO_D.replace("4827.94", "'fx'"), r": camera_matrix\.data must hold finite numbers, got 'fx'"),
    ("ros K short", ROS_NO_D.replace("0, 0, 1]", "0, 0]"), r": camera_matrix\.data must be 9 numbers"),
    ("ros rows", ROS_NO_D.replace("rows: 3", "rows: three"), r": camera_matrix\.rows must be an integer, got 'three'"),
    ("ros NaN", ROS_NO_D.replace("4827.94", ".nan"), r": camera_matrix\.data must hold finite numbers, got nan"),
    (
        "ros equidistant",
        ROS_FILE.replace("plumb_bob", "equidistant"),
        r": distortion_model 'equidistant' is not supported",
    ),
    (
        "ros 8 plumb_bob",
        ROS_RATIONAL.replace("rational_polynomial", "plumb_bob"),
        r": distortion_coefficients\.data must be 0 or 4 or 5 numbers",
    ),
    (
        "ros rows x cols",
        ROS_FILE.replace("cols: 5", "cols: 4"),
        r": distortion_coefficients has rows \* cols = 1 \* 4 but 5 data",
    ),
    ("ros width 0", ROS_FILE.replace("2448", "0"), r": image_size must be 1 to 100000"),
    ("ros deep", "image_width: " + "[" * 30_000 + "]" * 30_000, r": not valid YAML \(nested too deeply\)"),
    ("ros huge int", ROS_FILE.replace("2448", "9" * 5000), r": not valid YAML"),
    ("ros python tag", "camera_matrix: !!python/object/apply:os.system ['echo no']\n", r": not valid YAML"),
    ("yaml too long", "a: [" + "1, " * 30_000 + "]\n", r": 90006 characters of YAML, more than 65536"),
    # Kalibr
    (
        "kalibr omni",
        KALIBR_FILE.split("cam1:")[0].replace("pinhole", "omni"),
        r": cam0\.camera_model 'omni' is not supported",
    ),
    (
        "kalibr equidistant",
        KALIBR_FILE.split("cam1:")[0].replace("radtan", "equidistant"),
        r": cam0\.distortion_model 'equidistant' is not supported",
    ),
    (
        "kalibr no intrinsics",
        KALIBR_FILE.split("cam1:")[0].replace("  intrinsics: [458.654, 457.296, 367.215, 248.375]\n", ""),
        r": no 'cam0\.intrinsics'",
    ),
    (
        "kalibr intrinsics text",
        KALIBR_FILE.split("cam1:")[0].replace("[458.654, 457.296, 367.215, 248.375]", "fu fv pu pv"),
        r": cam0\.intrinsics must be 4 numbers",
    ),
    (
        "kalibr resolution",
        KALIBR_FILE.split("cam1:")[0].replace("[752, 480]", "['752', 480]"),
        r": cam0\.resolution must be an integer, got '752'",
    ),
    (
        "kalibr fy/fx",
        KALIBR_FILE.split("cam1:")[0].replace("457.296", "1400.0"),
        r"#cam0: K must have fy / fx in \[0.5, 2\]",
    ),
    # COLMAP
    (
        "colmap fisheye",
        "1 OPENCV_FISHEYE 640 480 500 500 320 240 0.1 0 0 0\n",
        r":1: MODEL OPENCV_FISHEYE is not supported",
    ),
    ("colmap params", "# c\n1 PINHOLE 640 480 500 500 320\n", r":2: PINHOLE needs 4 PARAMS \(fx fy cx cy\), got 3"),
    ("colmap nan", "1 PINHOLE 640 480 nan 500 320 240\n", r":1: PARAMS must be finite numbers, got 'nan'"),
    ("colmap underscore", "1 PINHOLE 640 480 5_00 500 320 240\n", r":1: PARAMS must be finite numbers, got '5_00'"),
    ("colmap broken line", "1 PINHOLE 640 480 500 500 320 240\n2 PINHOLE\n", r":2: not a camera line"),
    (
        "colmap twice",
        "1 PINHOLE 640 480 500 500 320 240\n1 PINHOLE 640 480 500 500 320 240\n",
        r":2: CAMERA_ID 1 appears twice",
    ),
    (
        "colmap far cx",
        "1 PINHOLE 640 480 500 500 5000 240\n",
        r"#1: K principal point .* outside the 640x480 px image",
    ),
    # mrcal
    ("mrcal code", "{'lensmodel': __import__('os').system('echo no')}", r": not a Python literal as mrcal writes one"),
    (
        "mrcal splined",
        "{'lensmodel': 'LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=30_Ny=18_fov_x_deg=150', 'intrinsics': []}",
        r": lensmodel 'LENSMODEL_SPLINED.*' is not supported \(OpenCV's pinhole models only: LENSMODEL_PINHOLE, ",
    ),
    (
        "mrcal count",
        "{'lensmodel': 'LENSMODEL_OPENCV4', 'intrinsics': [1000, 1000, 50, 40], 'imagersize': [100, 80]}",
        r": intrinsics must be 8 numbers",
    ),
    (
        "mrcal inf",
        "{'lensmodel': 'LENSMODEL_PINHOLE', 'intrinsics': [1e999, 1000, 50, 40], 'imagersize': [100, 80]}",
        r": intrinsics must hold finite numbers, got inf",
    ),
    ("mrcal no size", "{'lensmodel': 'LENSMODEL_PINHOLE', 'intrinsics': [1000, 1000, 50, 40]}", r": no 'imagersize'"),
    ("mrcal tokens", "{'lensmodel': 'x', 'a': 'b'" + "+1" * 200_000 + "}", r": more than 10000 Python tokens"),
    (
        "mrcal parens",
        "{'lensmodel': " + "(" * 300 + ")" * 300 + "}",
        r": not a Python literal as mrcal writes one \(too many nested parentheses",
    ),
    ("mrcal bad number", "{'lensmodel': 'LENSMODEL_PINHOLE', 'intrinsics': [1000x]}", r": not a Python literal"),
    (
        "mrcal unclosed",
        "{'lensmodel': 'LENSMODEL_PINHOLE',\n 'intrinsics': [1, 2,",
        r": not a Python literal as mrcal writes one",
    ),
    # Issue 33: integer matrices, octal, YAML 1.1's sexagesimal and 1_000, negative rows,
    # implausible focal lengths, digits that are not ASCII.
    (
        "cv dt u",
        CV_K.replace("dt: d", "dt: u") + CV_DATA,
        r": camera_matrix must be a matrix of dt f or d .*got dt 'u'",
    ),
    (
        "cv dt i",
        CV_K.replace("dt: d", "dt: i") + CV_DATA,
        r": camera_matrix must be a matrix of dt f or d .*got dt 'i'",
    ),
    (
        "cv dist dt i",
        CV_K
        + CV_DATA
        + "distortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: i\n   data: [0, 0, 0, 0, 1]\n",
        r": distortion_coefficients must be a matrix of dt f or d",
    ),
    (
        "cv size dt u",
        "%YAML:1.0\n---\ncameraResolution: !!opencv-matrix\n   rows: 1\n   cols: 2\n   dt: u\n   data: [640, 480]\n"
        + CV_K.split("---\n")[1].split("camera_matrix")[0].replace("image_width: 640\nimage_height: 480\n", "")
        + "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        + CV_DATA,
        r": cameraResolution must be a matrix of dt i or f or d",
    ),
    (
        "cv octal width",
        CV_K.replace("640", "0640") + CV_DATA,
        r":3: 0640 has a leading zero, which OpenCV reads as an octal number",
    ),
    ("cv octal in data", CV_K + CV_DATA.replace("320", "0320"), r":9: 0320 has a leading zero"),
    (
        "xml octal width",
        '<?xml version="1.0"?>\n<opencv_storage>\n<image_width>0640</image_width></opencv_storage>\n',
        r":3: 0640 has a leading zero",
    ),
    ("cv sexagesimal", CV_K + CV_DATA.replace("500, 0, 320", "8:20, 0, 320"), r": not a valid OpenCV YAML file"),
    (
        "ros rows -3",
        ROS_FILE.replace("rows: 3\n  cols: 3", "rows: -3\n  cols: -3"),
        r": camera_matrix must have rows, cols >= 1",
    ),
    (
        "ros sexagesimal fx",
        ROS_FILE.replace("4827.94", "80:27"),
        r": camera_matrix\.data must hold finite numbers, got '80:27'",
    ),
    ("ros 1_000 width", ROS_FILE.replace("2448", "2_448"), r": image_width must be an integer, got '2_448'"),
    ("ros yes width", ROS_FILE.replace("2448", "yes"), r": image_width must be an integer, got 'yes'"),
    (
        "json fx 5e-324",
        JSON_K.format(f=5e-324),
        r": K must have fx, fy within 0\.1 to 50 times the image's larger side",
    ),
    (
        "json fx 1e-300",
        JSON_K.format(f=1e-300),
        r": K must have fx, fy within 0\.1 to 50 times .*\(64 to 32000 px",
    ),
    ("json fx 1e300", JSON_K.format(f=1e300), r": K must have fx, fy within"),
    ("json fx 0.001", JSON_K.format(f=0.001), r": K must have fx, fy within"),
    ("json fx 63.9", JSON_K.format(f=63.9), r": K must have fx, fy within"),
    ("json fx 32001", JSON_K.format(f=32001.0), r": K must have fx, fy within"),
    (
        "colmap arabic-indic size",
        "1 PINHOLE \u0666\u0664\u0660 480 500 500 320 240\n",
        r": not a camera file of a known format",
    ),
    (
        "colmap full-width param",
        "1 PINHOLE 640 480 \uff15\uff10\uff10 500 320 240\n",
        r":1: PARAMS must be finite numbers",
    ),
    # camera.json
    (
        "json dist",
        '{"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "image_size": [640, 480], "dist_coeffs": [0.1, 0, 0]}',
        r": dist_coeffs must be 4 or 5 or 8 or 12 or 14 numbers",
    ),
    (
        "json dist NaN",
        '{"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "image_size": [640, 480], "dist_coeffs": [NaN, 0, 0, 0]}',
        r": dist_coeffs must hold finite numbers, got nan",
    ),
    (
        "json dist huge",
        '{"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "image_size": [640, 480], "dist_coeffs": [1e6, 0, 0, 0]}',
        r": dist_coeffs must be finite numbers of magnitude <= 1000",
    ),
]


@pytest.mark.parametrize(("content", "message"), [h[1:] for h in HOSTILE], ids=[h[0] for h in HOSTILE])
def test_every_wrong_or_hostile_file_is_one_camera_error_naming_the_file(tmp_path, content, message):
    path = write(tmp_path, content)
    with pytest.raises(CameraError, match=rf"^{re.escape(str(path))}{message}") as exc:
        read_camera(path)
    assert "\n" not in str(exc.value) and len(str(exc.value)) < 400


def test_a_refused_file_warns_nothing(tmp_path, recwarn):
    """Python's parser warns of "1or 2" (SyntaxWarning): a second line on stderr, were it shown."""
    with pytest.raises(CameraError, match=r"not a Python literal as mrcal writes one"):
        read_camera(write(tmp_path, "{'lensmodel': 'LENSMODEL_PINHOLE',\n 'intrinsics': [1or 2]}"))
    assert not recwarn.list


def test_billion_laughs_yaml_is_refused_without_expanding_it(tmp_path):
    laughs = "a: &a [" + ",".join(["lol"] * 9) + "]\n"
    laughs += "".join(f"{chr(98 + i)}: &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 9) + "]\n" for i in range(8))
    laughs += "camera_matrix: {rows: 3, cols: 3, data: *i}\nimage_width: 10\nimage_height: 10\n"
    path = write(tmp_path, laughs)
    with pytest.raises(CameraError, match=r"camera_matrix\.data must hold finite numbers, got \[\[\[\["):
        read_camera(path)


def test_missing_huge_and_folder_files_are_refused_naming_the_file(tmp_path):
    with pytest.raises(CameraError, match=r"missing\.yaml: cannot read the camera file"):
        read_camera(tmp_path / "missing.yaml")
    with pytest.raises(CameraError, match=r"cannot read the camera file"):
        read_camera(tmp_path)
    huge = write(tmp_path, mrcal_file(b"") + "#" * MAX_CAMERA_BYTES, "huge.cameramodel")
    with pytest.raises(CameraError, match=rf"huge\.cameramodel: larger than {MAX_CAMERA_BYTES} bytes"):
        read_camera(huge)


def test_the_nesting_bound_counts_what_can_open_a_level_and_not_numbers(tmp_path):
    """A calibration file's negative numbers and exponents are no nesting: 200 000 of them pass."""
    data = ", ".join(["-1.5e-05", "-2.", "-.5", "3.0e+02"] * 50_000)
    text = f"%YAML:1.0\n---\nm: !!opencv-matrix\n   rows: 1\n   cols: 200000\n   dt: d\n   data: [ {data} ]\n"
    assert len(opencv._YAML_OPENERS.findall(text)) == 11  # ':' 6, '-' 4 ('---', 'opencv-'), '[' 1
    assert len(opencv._YAML_OPENERS.findall("- - [a: {b")) == 5
    path = write(tmp_path, OPENCV_SAMPLE_YAML + "image_points: !!opencv-matrix" + text.split("!!opencv-matrix")[1])
    assert_same(read_camera(path), *OPENCV_SAMPLE)


def test_values_shortest_and_padded():
    assert values.shortest(None) is None
    np.testing.assert_array_equal(values.shortest([*D4, 0.0, 0.0, 0.0, 0.0]), D4)
    np.testing.assert_array_equal(values.shortest([*D5, 0.0, 0.0, 0.0]), D5)
    np.testing.assert_array_equal(values.shortest([*D4, 0.0, 0.0, 0.0, 1e-3]), [*D4, 0.0, 0.0, 0.0, 1e-3])
    assert values.shortest([1.0, 2.0, 3.0]).tolist() == [1.0, 2.0, 3.0]  # no OpenCV count: left to be refused
    assert values.padded(camera(), (5, 8), "x", "ROS") == [0.0] * 5
    assert values.padded(camera(D5), (4, 8), "x", "COLMAP") == [*D5, 0.0, 0.0, 0.0]
    assert values.yaml_number(1e-05) == "1.0e-05" and values.yaml_number(2.5e20) == "2.5e+20"
    assert mrcal.KEY.search("{\n 'lensmodel': 'LENSMODEL_PINHOLE'") and not mrcal.KEY.search('{"K": 1}')


def test_yaml_is_read_as_yaml_1_2_core_as_ros_reads_it(tmp_path):
    """ROS reads camera_info with yaml-cpp (YAML 1.2): 02448 is 2448 (PyYAML's 1.1 rule: octal 1320),
    0x802 is 2050, 1.97e-3 a float; Kalibr's resolution likewise."""
    ros = read_camera(write(tmp_path, ROS_FILE.replace("2448", "02448").replace("2050", "0x802"), "ros.yaml"))
    assert ros.image_size == (2448, 2050)
    lens = read_camera(write(tmp_path, ROS_FILE.replace("-0.00197", "-1.97e-3").replace("0.00071", "7.1e-4"), "e.yaml"))
    assert lens.dist_coeffs[2:4].tolist() == [-1.97e-3, 7.1e-4]
    kalibr = read_camera(write(tmp_path, KALIBR_FILE.replace("[752, 480]", "[0752, 0480]"), "camchain.yaml"), "cam0")
    assert kalibr.image_size == (752, 480)


def test_octal_looking_digits_in_strings_comments_and_floats_are_not_refused(tmp_path):
    text = (
        CV_K.replace("640", "640.0")
        + CV_DATA.replace("500, 0, 320", "0500.0, 0, 320")
        + 'calibration_time: "Thu 02 May 2024 10:03:07"\nserial: cam_0123\n# frames 007\n'
    )
    assert read_camera(write(tmp_path, text)).K[0, 0] == 500.0


@pytest.mark.parametrize("selector", ["\u0661", "\uff12", "\u0662", "2\u0660"])
def test_a_camera_selector_of_non_ascii_digits_names_no_camera(tmp_path, selector):
    path = write(tmp_path, COLMAP_FILE, "cameras.txt")
    with pytest.raises(CameraError, match=r"cameras\.txt: no camera '.*' \(it holds 1, 2, 3\)"):
        read_camera(f"{path}#{selector}")


def test_the_focal_bound_is_relative_to_the_larger_side(tmp_path):
    assert FOCAL_PER_SIDE == (0.1, 50.0)
    for f in (64.0, 32_000.0):  # 0.1 and 50 times 640 px: the bounds themselves pass
        assert read_camera(write(tmp_path, JSON_K.format(f=f), "cam.json")).K[0, 0] == f
    for f in (63.9, 4.25, 32_001.0):
        with pytest.raises(CameraError, match=r"must have fx, fy within 0\.1 to 50 times the image's larger side"):
            read_camera(write(tmp_path, JSON_K.format(f=f), "cam.json"))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX FIFOs")
def test_a_fifo_without_a_writer_is_refused_at_once_not_waited_on(tmp_path):
    fifo = tmp_path / "cam.yaml"
    os.mkfifo(fifo)
    start = time.monotonic()
    with pytest.raises(CameraError, match=r"cam\.yaml: cannot read the camera file \(a FIFO, not a regular file\)"):
        read_camera(fifo)
    with pytest.raises(CameraError, match=r"cannot read the camera file \(a FIFO"):
        read_camera(f"{fifo}#cam0")
    assert time.monotonic() - start < 5
