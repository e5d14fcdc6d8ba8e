"""Kalibr camchain YAML (``camchain.yaml``, ``camchain-imucam.yaml``): one entry per camera,
``cam0``, ``cam1``, ..., each with ``camera_model``, ``intrinsics`` [fu, fv, pu, pv] px,
``distortion_model``, ``distortion_coeffs`` and ``resolution`` [w, h] px. OpenCV's pixel
convention. The other keys (``T_cn_cnm1``, ``T_cam_imu``, ``rostopic``, ...) are not read.

``camera_model``: ``pinhole`` only (``omni``, ``eucm``, ``ds`` are refused).
``distortion_model``: ``radtan`` [k1, k2, r1, r2] (OpenCV's k1, k2, p1, p2) or ``none``;
``equidistant`` (fisheye), ``fov`` and any other are refused. A file with several cameras needs
one named (``FILE#cam1``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Optional

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.cameras import values
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.rectify.user_camera import Camera

DISTORTIONS = {"radtan": (4,), "none": (0,)}  # distortion_model -> distortion_coeffs counts
CAMERA = "cam0"  # the camera written


def cameras(d: Any) -> list[str]:
    """The names of the cameras of a parsed YAML value (entries with a ``camera_model``)."""
    if not isinstance(d, dict):
        return []
    return [k for k, v in d.items() if isinstance(k, str) and isinstance(v, Mapping) and "camera_model" in v]


def _choice(cam: dict, name: str, key: str, allowed: tuple, source: str) -> str:
    value = values.required(cam, key, source, f"{name}.")
    if not isinstance(value, str) or value not in allowed:
        raise CameraError(
            f"{source}: {name}.{key} {values.shown(value)} is not supported "
            f"(OpenCV's pinhole models only: {', '.join(allowed)})"
        )
    return value


def read(d: Any, source: str, name: Optional[str]) -> Camera:
    """The camera ``name`` (None: the only one) of a parsed camchain YAML mapping."""
    name = values.select(cameras(d), name, source)
    cam = dict(d[name])
    _choice(cam, name, "camera_model", ("pinhole",), source)
    model = _choice(cam, name, "distortion_model", tuple(DISTORTIONS), source)
    fu, fv, pu, pv = values.numbers(
        values.required(cam, "intrinsics", source, f"{name}."), (4,), source, f"{name}.intrinsics"
    )
    dist = values.numbers(cam.get("distortion_coeffs", []), DISTORTIONS[model], source, f"{name}.distortion_coeffs")
    size = values.required(cam, "resolution", source, f"{name}.")
    if not isinstance(size, list) or len(size) != 2:
        raise values.fail(source, f"{name}.resolution", f"must be 2 integers (width, height), got {values.shown(size)}")
    width, height = (values.whole(v, source, f"{name}.resolution") for v in size)
    return values.camera(k_matrix([fu, fv, pu, pv]), (width, height), f"{source}#{name}", dist or None)


def write(camera: Camera, source: str) -> str:
    """The camera as a one-camera camchain (``cam0``; no distortion: radtan, 4 zeros)."""
    dist = values.padded(camera, (4,), source, "Kalibr radtan")
    width, height = camera.image_size
    return (
        f"{CAMERA}:\n"
        "  camera_model: pinhole\n"
        f"  intrinsics: {values.yaml_list(k_params(camera.K))}\n"
        "  distortion_model: radtan\n"
        f"  distortion_coeffs: {values.yaml_list(dist)}\n"
        f"  resolution: [{width}, {height}]\n"
    )
