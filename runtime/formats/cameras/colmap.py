"""COLMAP ``cameras.txt``: ``#`` comment lines and one line per camera,
``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV and dimenet at (0, 0): so
cx = cx_COLMAP - 0.5 and cy = cy_COLMAP - 0.5 when read, + 0.5 when written (f unchanged).

Models read (PARAMS; k is k1; the distortion in OpenCV's order k1, k2, p1, p2, k3, k4, k5, k6):
SIMPLE_PINHOLE f cx cy; PINHOLE fx fy cx cy; SIMPLE_RADIAL f cx cy k; RADIAL f cx cy k1 k2;
OPENCV fx fy cx cy k1 k2 p1 p2; FULL_OPENCV fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6. The fisheye and
other models are refused. Written: PINHOLE without distortion, OPENCV with 4 coefficients,
FULL_OPENCV with 5 or 8. A file with several cameras needs one named by its ID (``FILE#2``).
"""

from __future__ import annotations

import re
from typing import Optional

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.cameras import values
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.rectify.user_camera import Camera

COLMAP_SHIFT_PX = 0.5  # x_COLMAP = x_OpenCV + 0.5 (and y)
MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
DISTORTION = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
# A data line begins ``CAMERA_ID MODEL WIDTH HEIGHT`` (how the format is told from the content).
# ASCII digits only (``\d`` would take Arabic-Indic and full-width digits, which int() reads).
LINE = re.compile(r"([0-9]{1,12})\s+([A-Za-z_]\w*)\s+([0-9]{1,12})\s+([0-9]{1,12})(\s|$)", re.ASCII)
_NUMBER = re.compile(r"[-+]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][-+]?[0-9]+)?")
_HEADER = "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"


def _data_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of the lines that are neither blank nor ``#`` comments."""
    lines = ((i, line.strip()) for i, line in enumerate(text.splitlines(), 1))
    return [(i, line) for i, line in lines if line and not line.startswith("#")]


def _params(tokens: list[str], where: str) -> list[float]:
    out = []
    for t in tokens:
        if not _NUMBER.fullmatch(t):
            raise CameraError(f"{where}: PARAMS must be finite numbers, got {values.shown(t)}")
        out.append(float(t))
    return out


def read(text: str, source: str, name: Optional[str]) -> Camera:
    """The camera whose CAMERA_ID is ``name`` (None: the only one) of a ``cameras.txt`` text."""
    rows = {}
    for i, line in _data_lines(text):
        m = LINE.match(line)
        if m is None:
            raise CameraError(
                f"{source}:{i}: not a camera line (CAMERA_ID MODEL WIDTH HEIGHT PARAMS...), got {values.shown(line)}"
            )
        camera_id = str(int(m.group(1)))
        if camera_id in rows:
            raise CameraError(f"{source}:{i}: CAMERA_ID {camera_id} appears twice")
        rows[camera_id] = (i, line.split())
    if name is not None and re.fullmatch(r"[0-9]{1,12}", name):
        name = str(int(name))  # "02" is camera 2
    camera_id = values.select(list(rows), name, source)
    i, (_, model, width, height, *tokens) = rows[camera_id]
    where = f"{source}:{i}"
    if model not in MODELS:
        raise CameraError(
            f"{where}: MODEL {model} is not supported (OpenCV's pinhole models only: {', '.join(MODELS)})"
        )
    if len(tokens) != len(MODELS[model]):
        raise CameraError(
            f"{where}: {model} needs {len(MODELS[model])} PARAMS ({' '.join(MODELS[model])}), got {len(tokens)}"
        )
    p = dict(zip(MODELS[model], _params(tokens, where)))
    fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
    K = k_matrix([fx, fy, p["cx"] - COLMAP_SHIFT_PX, p["cy"] - COLMAP_SHIFT_PX])
    dist = [p.get(k, 0.0) for k in DISTORTION]
    return values.camera(K, (int(width), int(height)), f"{source}#{camera_id}", dist)


def write(camera: Camera, source: str) -> str:
    """The camera as a one-camera ``cameras.txt`` (CAMERA_ID 1), COLMAP's header comments first."""
    fx, fy, cx, cy = (float(v) for v in k_params(camera.K))
    dist = [] if camera.dist_coeffs is None else values.padded(camera, (4, 8), source, "COLMAP OPENCV or FULL_OPENCV")
    model = {0: "PINHOLE", 4: "OPENCV", 8: "FULL_OPENCV"}[len(dist)]
    params = [fx, fy, cx + COLMAP_SHIFT_PX, cy + COLMAP_SHIFT_PX, *dist]
    width, height = camera.image_size
    line = " ".join(["1", model, str(width), str(height), *(values.number(v) for v in params)])
    return f"{_HEADER}# Number of cameras: 1\n{line}\n"
