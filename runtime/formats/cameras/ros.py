"""ROS ``camera_info`` YAML, as camera_calibration_parsers reads and writes it (the file of
``camera_info_url``): ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix``,
``distortion_model``, ``distortion_coefficients``, ``rectification_matrix``,
``projection_matrix``, each matrix ``{rows, cols, data}`` row by row. OpenCV's pixel convention.

K and the distortion are the raw image's. The rectification and projection matrices (of the
rectified image, a stereo pair's) are not read; they are written as the identity and [K | 0].
``distortion_model``: ``plumb_bob`` (k1, k2, p1, p2, k3; ROS assumes it when absent) and
``rational_polynomial`` (k1, k2, p1, p2, k3, k4, k5, k6) are OpenCV's models; ``equidistant``
(fisheye) and any other is refused.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.cameras import values
from dimenet.runtime.rectify.user_camera import Camera

# distortion_model -> the coefficient counts read (0: an empty list, no distortion), and written
MODELS = {"plumb_bob": (0, 4, 5), "rational_polynomial": (8,)}
CAMERA_NAME = "camera"  # camera_name written


def _matrix(d: dict, key: str, counts: tuple, source: str) -> list[float]:
    """The ``data`` of the matrix ``key`` ({rows, cols, data}): rows * cols numbers, one of ``counts``."""
    m = values.mapping(values.required(d, key, source), source, key)
    rows, cols = (
        values.whole(values.required(m, k, source, f"{key}."), source, f"{key}.{k}") for k in ("rows", "cols")
    )
    if rows < 1 or cols < 1:
        raise values.fail(source, key, f"must have rows, cols >= 1, got rows = {rows}, cols = {cols}")
    data = values.numbers(values.required(m, "data", source, f"{key}."), counts, source, f"{key}.data")
    if rows * cols != len(data):
        raise values.fail(source, key, f"has rows * cols = {rows} * {cols} but {len(data)} data")
    return data


def is_ros(d: Any) -> bool:
    """Whether a parsed YAML value is a camera_info file (it has a ``camera_matrix``)."""
    return isinstance(d, dict) and "camera_matrix" in d


def read(d: Any, source: str) -> Camera:
    """The camera of a parsed camera_info YAML mapping."""
    d = values.mapping(d, source, "the camera file")
    model = d.get("distortion_model", "plumb_bob")
    if not isinstance(model, str) or model not in MODELS:
        raise CameraError(
            f"{source}: distortion_model {values.shown(model)} is not supported "
            f"(OpenCV's pinhole models only: {', '.join(MODELS)})"
        )
    K = _matrix(d, "camera_matrix", (9,), source)
    dist = _matrix(d, "distortion_coefficients", MODELS[model], source) if "distortion_coefficients" in d else None
    width, height = (values.whole(values.required(d, k, source), source, k) for k in ("image_width", "image_height"))
    return values.camera(np.reshape(K, (3, 3)), (width, height), source, dist or None)


def write(camera: Camera, source: str) -> str:
    """The camera as camera_calibration_parsers' YAML (no distortion: plumb_bob, 5 zeros)."""
    dist = values.padded(camera, (5, 8), source, "ROS camera_info (plumb_bob 5, rational_polynomial 8)")
    model = "plumb_bob" if len(dist) == 5 else "rational_polynomial"
    P = [*camera.K[0], 0.0, *camera.K[1], 0.0, *camera.K[2], 0.0]

    def matrix(key: str, rows: int, cols: int, data) -> str:
        return f"{key}:\n  rows: {rows}\n  cols: {cols}\n  data: {values.yaml_list(data)}\n"

    return (
        f"image_width: {camera.image_size[0]}\nimage_height: {camera.image_size[1]}\ncamera_name: {CAMERA_NAME}\n"
        + matrix("camera_matrix", 3, 3, camera.K.reshape(-1))
        + f"distortion_model: {model}\n"
        + matrix("distortion_coefficients", 1, len(dist), dist)
        + matrix("rectification_matrix", 3, 3, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
        + matrix("projection_matrix", 3, 4, P)
    )
