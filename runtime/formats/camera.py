"""Camera file (``camera.json``): a camera's fixed intrinsic matrix K_c and its image size.

Specified in ``models_spec/camera-json.md``. The file is UTF-8 JSON,
``{"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "image_size": [w, h]}``, in pixels, OpenCV's
pixel convention (the centre of the top-left pixel at (0, 0)), image size as (width, height).
Only ``K`` and ``image_size`` are read; other keys (e.g. ``dist_coeffs``) are ignored.
The values are then checked as the runtime checks a camera given in memory
(``rectify.camera.checked_camera``). Every problem is a CameraError (a ValueError) naming
the file and the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.text import read_text
from dimenet.runtime.json_text import JsonProblem, an_object, integer, parse_json, required, shown
from dimenet.runtime.json_text import numbers as json_numbers
from dimenet.runtime.rectify.camera import MAX_IMAGE_SIDE_PX, Camera, checked_camera

MAX_CAMERA_BYTES = 64 << 10  # a camera file: 64 KiB of JSON (one is ~100 bytes)


def _json_camera(d: Any, source: str) -> Camera:
    try:
        d = an_object(d, "the camera file")
        K = json_numbers(required(d, "K"), (3, 3), "K")
        size = required(d, "image_size")
        if not isinstance(size, list) or len(size) != 2:
            raise JsonProblem(f"image_size must be 2 integers (width, height), got {shown(size)}")
        width, height = (integer(v, "image_size", 1, MAX_IMAGE_SIDE_PX) for v in size)
    except JsonProblem as exc:
        raise CameraError(f"{source}: {exc}") from None
    return checked_camera(K, (width, height), source)


def read_camera(path: str | Path) -> Camera:
    """Read and check a camera JSON file (UTF-8, a BOM ignored, at most ``MAX_CAMERA_BYTES``).
    Raises CameraError naming the file and the field."""
    path = Path(path)
    text = read_text(path, MAX_CAMERA_BYTES, "camera file", CameraError)
    try:
        d = parse_json(text, max_chars=MAX_CAMERA_BYTES)
    except JsonProblem as exc:
        raise CameraError(f"{path}: not valid JSON ({exc})" if exc.line else f"{path}: {exc.problem}") from None
    return _json_camera(d, str(path))
