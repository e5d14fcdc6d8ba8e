"""Camera files: a camera's K (3x3 px), image size (width, height) px and lens distortion, in
the formats of OpenCV, ROS, COLMAP, Kalibr, mrcal and dimenet's own ``camera.json``.

Specified in ``models_spec/camera-files.md``; one module per format in ``formats.cameras``.
Every camera is in OpenCV's pixel convention (the centre of the top-left pixel at (0, 0);
COLMAP's 0.5 px shift is applied on the way in and out) with OpenCV's distortion coefficients
(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]), checked as a camera given in memory
is (``rectify.user_camera.checked_camera``), its distortion in shortest form (trailing zeros dropped
down to 4, 5, 8 or 12 coefficients; none when all are 0).

``read_camera`` tells the format from the file's content, not its suffix. A file holding
several cameras (Kalibr cam0, cam1; COLMAP one line per camera) needs one named: ``name=``, or
``FILE#NAME`` (``cams.txt#2``, ``camchain.yaml#cam1``). Every problem is a one-line CameraError
(a ValueError) naming the file and the field.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.atomic import atomic_write_text
from dimenet.runtime.formats.cameras import colmap, json_file, kalibr, mrcal, opencv, ros, values
from dimenet.runtime.formats.text import read_text
from dimenet.runtime.json_text import JsonProblem, parse_json
from dimenet.runtime.rectify.user_camera import Camera

# A camera file is at most 16 MiB: a mrcal model carries its optimization inputs (MBs of
# base-85), an OpenCV calibration its image points; a pinhole camera alone is ~1 KiB.
MAX_CAMERA_BYTES = 16 << 20

FORMATS = ("opencv-yaml", "opencv-xml", "ros", "colmap", "kalibr", "mrcal", "json")
MULTI_CAMERA_FORMATS = ("colmap", "kalibr")  # the formats whose files may hold several cameras
# The format a suffix names (``.yaml``/``.yml`` do not: OpenCV, ROS and Kalibr all use them).
SUFFIX_FORMATS = {".json": "json", ".xml": "opencv-xml", ".txt": "colmap", ".cameramodel": "mrcal"}

# format -> reader of (what _detect gives, source, camera name)
_READERS: dict[str, Callable[[Any, str, Optional[str]], Camera]] = {
    "opencv-yaml": lambda text, source, _: opencv.read(text, source, xml=False),
    "opencv-xml": lambda text, source, _: opencv.read(text, source, xml=True),
    "ros": lambda d, source, _: ros.read(d, source),
    "colmap": colmap.read,
    "kalibr": kalibr.read,
    "mrcal": lambda text, source, _: mrcal.read(text, source),
    "json": lambda d, source, _: json_file.read(d, source),
}
_WRITERS: dict[str, Callable[[Camera, str], str]] = {
    "opencv-yaml": lambda camera, source: opencv.write(camera, source, xml=False),
    "opencv-xml": lambda camera, source: opencv.write(camera, source, xml=True),
    "ros": ros.write,
    "colmap": colmap.write,
    "kalibr": kalibr.write,
    "mrcal": mrcal.write,
    "json": json_file.write,
}


def format_for_suffix(path: str | Path) -> Optional[str]:
    """The format the file name's suffix names (SUFFIX_FORMATS), or None."""
    return SUFFIX_FORMATS.get(Path(path).suffix.lower())


def _head(text: str) -> str:
    """The first line that is neither blank nor a ``#`` comment, stripped ("" if none)."""
    return next((s for s in (line.strip() for line in text.splitlines()) if s and not s.startswith("#")), "")


def _detect(text: str, source: str) -> tuple[str, Any]:
    """(format, what its reader takes: the text, or the parsed JSON or YAML value)."""
    head = _head(text)
    if head.startswith("<"):
        return "opencv-xml", text
    if "opencv-matrix" in text or head.startswith("%YAML:"):
        return "opencv-yaml", text
    if head.startswith("{") and mrcal.KEY.search(text):
        return "mrcal", text
    if colmap.LINE.match(head):
        return "colmap", text
    if not head or head[0] in "[{":
        return "json", json_file.parsed(text, source, MAX_CAMERA_BYTES)
    try:
        return "json", parse_json(text, max_chars=MAX_CAMERA_BYTES)  # a bare JSON value, "3000"
    except JsonProblem:
        pass
    d = values.load_yaml(text, source)
    if ros.is_ros(d):
        return "ros", d
    if kalibr.cameras(d):
        return "kalibr", d
    raise CameraError(
        f"{source}: not a camera file of a known format (OpenCV YAML or XML, ROS camera_info, COLMAP cameras.txt, "
        "Kalibr camchain, mrcal .cameramodel, camera.json)"
    )


def camera_file(path: str | Path) -> tuple[str, Optional[str]]:
    """(the file, the camera name or None) of a ``FILE#NAME`` path; a file whose own name has a
    ``#`` is that file."""
    if "#" in str(path) and not os.path.exists(path):
        file, name = str(path).rsplit("#", 1)
        return file, name
    return str(path), None


def read_camera(path: str | Path, name: Optional[str] = None) -> Camera:
    """The camera of the file ``path`` in any of FORMATS, told from its content (UTF-8, a BOM
    ignored, at most MAX_CAMERA_BYTES). ``name`` chooses one camera of a multi-camera file
    (a COLMAP CAMERA_ID, a Kalibr camN); without it, a ``path`` ending in ``#NAME`` does,
    unless a file of that very name exists. Raises CameraError naming the file and the field."""
    if name is None:
        path, name = camera_file(path)
    path = Path(path)
    text = read_text(path, MAX_CAMERA_BYTES, "camera file", CameraError)
    source = str(path)
    fmt, content = _detect(text, source)
    if name is not None and fmt not in MULTI_CAMERA_FORMATS:
        raise CameraError(f"{source}: a {fmt} file holds one camera, there is none to choose as #{name}")
    return _READERS[fmt](content, source, name)


def write_camera(path: str | Path, camera: Camera, format: str) -> Path:
    """Write ``camera`` as a file of ``format`` (one of FORMATS) atomically; returns the path.
    CameraError when the format cannot hold the camera's distortion (e.g. 14 coefficients in
    COLMAP, or coefficients stated about another K than the camera's); WriteError (an OSError)
    when the file cannot be written."""
    if format not in _WRITERS:
        raise CameraError(f"{path}: unknown camera format {format!r} (one of {', '.join(FORMATS)})")
    if camera.dist_coeffs is not None and camera.dist_K is not None and not np.array_equal(camera.dist_K, camera.K):
        raise CameraError(
            f"{path}: dist_coeffs are stated about another K (dist_K) and a camera file states them about its own K"
        )
    return atomic_write_text(path, _WRITERS[format](camera, str(path)))
