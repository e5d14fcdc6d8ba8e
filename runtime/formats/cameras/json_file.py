"""dimenet's ``camera.json``: ``{"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "image_size": [w, h]}``
in px, OpenCV's pixel convention, and optionally ``"dist_coeffs": [k1, k2, p1, p2, ...]``
(OpenCV's order, 4/5/8/12/14 of them). Other keys are ignored."""

from __future__ import annotations

import json
from typing import Any

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.cameras import values
from dimenet.runtime.json_text import JsonProblem, an_object, integer, parse_json, required, shown
from dimenet.runtime.json_text import numbers as json_numbers
from dimenet.runtime.rectify.user_camera import DIST_COEFF_COUNTS, MAX_IMAGE_SIDE_PX, Camera


def parsed(text: str, source: str, max_chars: int) -> Any:
    """The JSON value of ``text``; CameraError ``not valid JSON`` (with the line) otherwise."""
    try:
        return parse_json(text, max_chars=max_chars)
    except JsonProblem as exc:
        raise CameraError(f"{source}: not valid JSON ({exc})" if exc.line else f"{source}: {exc.problem}") from None


def read(d: Any, source: str) -> Camera:
    """The camera of a parsed ``camera.json`` value."""
    try:
        d = an_object(d, "the camera file")
        K = json_numbers(required(d, "K"), (3, 3), "K")
        size = required(d, "image_size")
        if not isinstance(size, list) or len(size) != 2:
            raise JsonProblem(f"image_size must be 2 integers (width, height), got {shown(size)}")
        width, height = (integer(v, "image_size", 1, MAX_IMAGE_SIDE_PX) for v in size)
    except JsonProblem as exc:
        raise CameraError(f"{source}: {exc}") from None
    dist = d.get("dist_coeffs")
    if dist is not None:
        dist = values.numbers(dist, DIST_COEFF_COUNTS, source, "dist_coeffs")
    return values.camera(K, (width, height), source, dist)


def write(camera: Camera, source: str) -> str:
    """The camera as ``camera.json`` text, one key a line (``dist_coeffs`` only when it has a
    distortion)."""
    d: dict[str, Any] = {"K": camera.K.tolist(), "image_size": list(camera.image_size)}
    if camera.dist_coeffs is not None:
        d["dist_coeffs"] = camera.dist_coeffs.tolist()
    return "{" + ",\n ".join(f"{json.dumps(k)}: {json.dumps(v)}" for k, v in d.items()) + "}\n"
