"""OpenCV FileStorage camera files, YAML (``!!opencv-matrix``) and XML (``<opencv_storage>``,
``type_id="opencv-matrix"``), read and written by ``cv2.FileStorage``. OpenCV's pixel convention.

Read: K from ``camera_matrix`` (OpenCV's calibration samples), ``cameraMatrix`` (its interactive
calibration) or ``K``; the distortion (k1, k2, p1, p2[, k3[, ...]]) from
``distortion_coefficients``, ``dist_coeffs``, ``distCoeffs`` or ``D`` (absent: none); the image
size from ``image_width`` and ``image_height``, or a (width, height) 2-vector
``cameraResolution``, ``imageSize`` or ``image_size``. Each is an opencv-matrix, an
opencv-nd-matrix (cv2's 1-D array) or a sequence of numbers. A fisheye calibration
(``fisheye_model`` not 0, ``calibrationModel`` not pinhole) is refused. Written: the
calibration sample's four keys.

Refused because cv2 would read them as no one means them: a matrix of K or the distortion
whose element type ``dt`` is not a float (``u`` stores 3000 as 255, ``i`` 2015.5 as 2016), an
image size of a type narrower than ``i``; an integer written with a leading zero (cv2 reads
``04032`` as octal, 2074), outside quoted strings and comments.

cv2's parsers recurse once per nesting level and overflow the native stack (a segfault, not an
exception) near 35000 levels, so a text reaches them only with at most MAX_STRUCTURES
characters that can open a level (YAML: ``[``, ``{``, ``:`` and a ``-`` that starts no number;
XML: ``<``). A calibration file has ~100, whatever the size of its matrices.
"""

from __future__ import annotations

import re
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.cameras import values
from dimenet.runtime.rectify.user_camera import Camera

K_KEYS = ("camera_matrix", "cameraMatrix", "K")
DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
SIZE_KEYS = ("cameraResolution", "imageSize", "image_size")
MAX_STRUCTURES = 1000
MAX_ELEMENTS = 16  # of a matrix read: K 9, a distortion at most 14, an image size 2

_YAML_OPENERS = re.compile(r"[\[{:]|-(?![0-9.])")
# A number cv2 reads as octal: a leading 0 and more digits, not inside a float, a word or a time.
_OCTAL = re.compile(r"(?<![\w.:+-])[-+]?0[0-9]+(?![\w.])", re.ASCII)
# What may hold such digits harmlessly: quoted strings, comments, XML's declaration.
_YAML_TEXT = re.compile(r"\"[^\"\n]*\"|'[^'\n]*'|#[^\n]*")
_XML_TEXT = re.compile(r"\"[^\"]*\"|'[^']*'|<!--.*?-->|<\?.*?\?>", re.DOTALL)
REAL_TYPES = ("f", "d")  # dt of K and the distortion: float, double
SIZE_TYPES = ("i", "f", "d")  # dt of an image size: also int (u, c, w, s truncate 4032)


def _kind(xml: bool) -> str:
    return "XML" if xml else "YAML"


def _reason(exc: Exception) -> str:
    """cv2's message without its source path: ``line 3: Missing , between the elements``."""
    if isinstance(exc, SystemError) and exc.__cause__ is not None:  # cv2's constructor wraps its error
        exc = exc.__cause__
    message = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
    message = re.sub(r"^\((\d+)\): ", r"line \1: ", message.split(" in function ", 1)[-1].strip("'"))
    return message[:120]


def _check_no_octal(text: str, source: str, xml: bool) -> None:
    """CameraError naming the line of an integer with a leading zero outside strings and comments."""
    blanked = (_XML_TEXT if xml else _YAML_TEXT).sub(lambda m: re.sub(r"[^\n]", " ", m.group()), text)
    m = _OCTAL.search(blanked)
    if m is not None:
        line = blanked.count("\n", 0, m.start()) + 1
        raise CameraError(
            f"{source}:{line}: {m.group()} has a leading zero, which OpenCV reads as an octal number: "
            f"write it without the zero"
        )


def _storage(text: str, source: str, xml: bool) -> cv2.FileStorage:
    openers = text.count("<") if xml else len(_YAML_OPENERS.findall(text))
    if openers > MAX_STRUCTURES:
        raise CameraError(
            f"{source}: {openers} nesting characters, more than {MAX_STRUCTURES} for an OpenCV camera file"
        )
    _check_no_octal(text, source, xml)
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:
        raise CameraError(f"{source}: not a valid OpenCV {_kind(xml)} file ({_reason(exc)})") from None
    if not fs.isOpened():
        raise CameraError(f"{source}: not a valid OpenCV {_kind(xml)} file")
    return fs


def _node(fs: cv2.FileStorage, keys: tuple) -> tuple[str, Optional[cv2.FileNode]]:
    """The first of ``keys`` the file has, and its node (None: none of them)."""
    for key in keys:
        node = fs.getNode(key)
        if not node.empty():
            return key, node
    return "/".join(keys), None


def _number(node: cv2.FileNode, source: str, field: str) -> float:
    if not (node.isInt() or node.isReal()):
        raise values.fail(source, field, "must be a number")
    return float(node.real())


def _integer(node: cv2.FileNode, source: str, field: str) -> int:
    v = _number(node, source, field)
    if not np.isfinite(v) or v != int(v):
        raise values.fail(source, field, f"must be an integer, got {v!r}")
    return int(v)


def _array(node: cv2.FileNode, source: str, field: str, types: tuple = REAL_TYPES) -> np.ndarray:
    """An opencv-matrix or opencv-nd-matrix (at most MAX_ELEMENTS, checked before cv2 allocates
    it, its element type ``dt`` one of ``types``) or a sequence of numbers, as float64 values in
    row order."""
    if node.isMap():
        dt = node.getNode("dt")
        dt = dt.string() if dt.isString() else None
        if dt not in types:
            raise values.fail(
                source, field, f"must be a matrix of dt {' or '.join(types)} (what cv2 stores it as), got dt {dt!r}"
            )
        sizes = node.getNode("sizes")  # an opencv-nd-matrix (what cv2 writes for a 1-D array)
        if sizes.empty():
            shape = [_integer(node.getNode(k), source, f"{field}.{k}") for k in ("rows", "cols")]
        elif not sizes.isSeq() or 1 <= sizes.size() <= 3:  # XML reads a 1-D size as one integer
            items = [sizes.at(i) for i in range(sizes.size())] if sizes.isSeq() else [sizes]
            shape = [_integer(item, source, f"{field}.sizes") for item in items]
        else:
            raise values.fail(source, field, "sizes must be 1 to 3 integers")
        if not (min(shape) >= 1 and int(np.prod(shape)) <= MAX_ELEMENTS):
            raise values.fail(source, field, f"must be a small matrix, got {' x '.join(map(str, shape))}")
        try:
            matrix = node.mat()
        except cv2.error as exc:
            raise values.fail(source, field, f"is not a valid opencv-matrix ({_reason(exc)})") from None
        if matrix is None:
            raise values.fail(source, field, "is not a valid opencv-matrix")
        return np.asarray(matrix, dtype=np.float64).reshape(-1)
    if node.isSeq() and 1 <= node.size() <= MAX_ELEMENTS:
        return np.array([_number(node.at(i), source, field) for i in range(node.size())])
    raise values.fail(source, field, f"must be an opencv-matrix or a sequence of at most {MAX_ELEMENTS} numbers")


def _image_size(fs: cv2.FileStorage, source: str) -> tuple[int, int]:
    if not (fs.getNode("image_width").empty() and fs.getNode("image_height").empty()):
        width, height = (_integer(_required(fs, key, source), source, key) for key in ("image_width", "image_height"))
        return width, height
    key, node = _node(fs, SIZE_KEYS)
    if node is None:
        raise CameraError(f"{source}: no image size (image_width and image_height, or {', '.join(SIZE_KEYS)})")
    size = _array(node, source, key, SIZE_TYPES)
    if size.size != 2 or not np.all(np.isfinite(size)) or np.any(size != np.round(size)):
        raise values.fail(source, key, f"must be 2 integers (width, height), got {size.tolist()}")
    return int(size[0]), int(size[1])


def _required(fs: cv2.FileStorage, key: str, source: str) -> cv2.FileNode:
    node = fs.getNode(key)
    if node.empty():
        raise CameraError(f"{source}: no {key!r}")
    return node


def _check_pinhole(fs: cv2.FileStorage, source: str) -> None:
    fisheye = fs.getNode("fisheye_model")
    if not fisheye.empty() and _number(fisheye, source, "fisheye_model") != 0:
        raise CameraError(
            f"{source}: fisheye_model: a fisheye calibration is not supported (OpenCV's pinhole model only)"
        )
    model = fs.getNode("calibrationModel")
    if not model.empty() and model.string() != "pinhole":
        raise CameraError(
            f"{source}: calibrationModel {model.string()!r} is not supported (OpenCV's pinhole model only)"
        )


def read(text: str, source: str, xml: bool) -> Camera:
    """The camera of an OpenCV FileStorage YAML (``xml`` False) or XML text."""
    fs = _storage(text, source, xml)
    try:
        _check_pinhole(fs, source)
        key, node = _node(fs, K_KEYS)
        if node is None:
            raise CameraError(f"{source}: no camera matrix ({', '.join(K_KEYS)})")
        K = _array(node, source, key)
        if K.size != 9:
            raise values.fail(source, key, f"must be 3 x 3 numbers, got {K.size}")
        size = _image_size(fs, source)
        dist_key, dist_node = _node(fs, DIST_KEYS)
        dist = None if dist_node is None else _array(dist_node, source, dist_key)
    finally:
        fs.release()
    return values.camera(K.reshape(3, 3), size, source, dist)


def write(camera: Camera, source: str, xml: bool) -> str:
    """The camera as OpenCV FileStorage text (no distortion: 5 zeros, as calibrateCamera's)."""
    fs = cv2.FileStorage(".xml" if xml else ".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("image_width", int(camera.image_size[0]))
    fs.write("image_height", int(camera.image_size[1]))
    fs.write("camera_matrix", np.array(camera.K))
    dist = np.zeros(5) if camera.dist_coeffs is None else np.array(camera.dist_coeffs)
    fs.write("distortion_coefficients", dist.reshape(-1, 1))
    return fs.releaseAndGetString()
