"""mrcal ``.cameramodel``: one Python dict literal with ``#`` comments, as mrcal's
``cameramodel.write`` makes it: ``'lensmodel'``, ``'intrinsics'`` [fx, fy, cx, cy, *distortion]
px, ``'extrinsics'`` (rt_fromref, not read; written as zeros), ``'imagersize'`` [w, h] px, and
perhaps ``'valid_intrinsics_region'``, ``'optimization_inputs'`` (a bytes literal), not read.
OpenCV's pixel convention. Parsed by ``ast.literal_eval`` (literals only, nothing is run) once
it has at most MAX_TOKENS Python tokens (the parser's work, whatever the size of a bytes literal).

``lensmodel``: LENSMODEL_PINHOLE and LENSMODEL_OPENCV4/5/8/12 (OpenCV's k1, k2, p1, p2[, k3[, k4,
k5, k6[, s1, s2, s3, s4]]]); the older keys ``lens_model`` and ``distortion_model``
(``DISTORTION_...``) as mrcal reads them. Other models (splined, CAHVOR, stereographic, ...)
are refused.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
import warnings
from typing import Any

from dimenet.runtime.errors import CameraError
from dimenet.runtime.formats.cameras import values
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.rectify.user_camera import Camera

MODELS = {
    "LENSMODEL_PINHOLE": 0,
    "LENSMODEL_OPENCV4": 4,
    "LENSMODEL_OPENCV5": 5,
    "LENSMODEL_OPENCV8": 8,
    "LENSMODEL_OPENCV12": 12,
}
MODEL_KEYS = ("lensmodel", "lens_model", "distortion_model")  # mrcal's key, then its older ones
# How the format is told from the content: a ``{`` whose dict has one of MODEL_KEYS.
KEY = re.compile(r"""['"](lensmodel|lens_model|distortion_model)['"]\s*:""")
MAX_TOKENS = 10_000  # a camera model has ~100, and a few hundred more with its valid-intrinsics contour


def _model(d: dict, source: str) -> tuple[str, int]:
    key = next((k for k in MODEL_KEYS if k in d), None)
    if key is None:
        raise CameraError(f"{source}: no 'lensmodel'")
    model = d[key]
    if isinstance(model, str):
        model = model.replace("DISTORTION_", "LENSMODEL_")
    if not isinstance(model, str) or model not in MODELS:
        raise CameraError(
            f"{source}: lensmodel {values.shown(d[key])} is not supported "
            f"(OpenCV's pinhole models only: {', '.join(MODELS)})"
        )
    return model, MODELS[model]


def _reason(exc: Exception) -> str:
    if isinstance(exc, SyntaxError):
        return f"{exc.msg}, line {exc.lineno}" if exc.lineno else str(exc.msg)
    text = str(exc).splitlines()[0][:80] if str(exc) else ""
    return text or type(exc).__name__


def _literal(text: str, source: str) -> Any:
    """The value of the Python literal ``text``, once it has at most MAX_TOKENS tokens."""
    tokens = tokenize.generate_tokens(io.StringIO(text).readline)
    try:
        too_many = any(count > MAX_TOKENS for count, _ in enumerate(tokens, 1))
        with warnings.catch_warnings():  # the parser's SyntaxWarnings would be a second line on stderr
            warnings.simplefilter("ignore")
            value = None if too_many else ast.literal_eval(text)
    except (ValueError, TypeError, SyntaxError, tokenize.TokenError, MemoryError, RecursionError) as exc:
        raise CameraError(f"{source}: not a Python literal as mrcal writes one ({_reason(exc)})") from None
    if too_many:
        raise CameraError(f"{source}: more than {MAX_TOKENS} Python tokens, too many for a camera model")
    return value


def read(text: str, source: str) -> Camera:
    """The camera of a ``.cameramodel`` text."""
    d = _literal(text, source)
    d = values.mapping(d, source, "the camera model")
    model, n = _model(d, source)
    intrinsics = values.numbers(values.required(d, "intrinsics", source), (4 + n,), source, "intrinsics")
    size = values.required(d, "imagersize", source)
    if not isinstance(size, (list, tuple)) or len(size) != 2:
        raise values.fail(source, "imagersize", f"must be 2 integers (width, height), got {values.shown(size)}")
    width, height = (values.whole(v, source, "imagersize") for v in size)
    return values.camera(k_matrix(intrinsics[:4]), (width, height), source, intrinsics[4:] or None)


def write(camera: Camera, source: str) -> str:
    """The camera as a ``.cameramodel`` (LENSMODEL_PINHOLE without distortion, else the
    LENSMODEL_OPENCVn that holds it), laid out as mrcal writes one."""
    dist = [] if camera.dist_coeffs is None else values.padded(camera, (4, 5, 8, 12), source, "mrcal LENSMODEL_OPENCVn")
    model = next(m for m, count in MODELS.items() if count == len(dist))

    def listed(vs) -> str:
        return "[ " + " ".join(f"{v}," for v in vs) + " ]"

    intrinsics = [values.number(v) for v in (*k_params(camera.K), *dist)]
    return (
        "# written by dimenet\n{\n"
        f"    'lensmodel':  '{model}',\n\n"
        "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n"
        f"    'intrinsics': {listed(intrinsics)},\n\n"
        "    # extrinsics are rt_fromref\n"
        f"    'extrinsics': {listed(['0.0'] * 6)},\n\n"
        f"    'imagersize': {listed(camera.image_size)},\n"
        "}\n"
    )
