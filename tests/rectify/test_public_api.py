"""What an app meets first: the names `dimenet.runtime` exports, their reprs, OpenCV's point shapes,
`python -m dimenet`, and the typing marker."""

from __future__ import annotations

import inspect
import subprocess
import sys
from importlib import resources

import numpy as np
from helpers import default_rectifier

import dimenet.runtime
from dimenet.runtime import errors
from dimenet.runtime.native import implementation


def test_every_error_of_the_errors_module_is_exported_and_a_value_error():
    defined = {name for name, obj in inspect.getmembers(errors, inspect.isclass) if obj.__module__ == errors.__name__}
    assert {"DimenetError", "PointsError", "CameraError", "InputError"} <= defined
    assert defined <= set(dimenet.runtime.__all__)
    for name in defined:
        assert issubclass(getattr(dimenet.runtime, name), ValueError)


def test_the_rectifier_says_what_it_serves():
    r = default_rectifier()
    text = repr(r)
    assert text.startswith("Rectifier(model=") and f"mode={r.mode!r}" in text
    assert f"image_size={r.image_size[0]}x{r.image_size[1]} px" in text and f"fx {r.K_c[0, 0]:.2f}" in text


def test_opencv_shaped_points_give_the_same_result(frames):
    r = default_rectifier()
    b = int(np.flatnonzero(frames.scene == "rig")[0])
    m = frames.valid[b]
    p2, p3 = frames.points_2d[b][m], frames.points_3d[b][m]
    flat = r.rectify(p2, p3)
    shaped = r.rectify(p2.reshape(-1, 1, 2), p3.reshape(-1, 1, 3))
    np.testing.assert_array_equal(shaped.K, flat.K)
    np.testing.assert_array_equal(shaped.tvec, flat.tvec)


def test_python_dash_m_dimenet_is_the_command_and_the_package_is_typed():
    done = subprocess.run([sys.executable, "-m", "dimenet", "--version"], capture_output=True, text=True, timeout=60)
    version = f"dimenet {dimenet.runtime.__version__} (implementation {implementation()})"
    assert done.returncode == 0 and done.stdout.strip() == version, done.stderr
    assert resources.files("dimenet.runtime").joinpath("py.typed").is_file()


def test_the_rectifier_s_public_methods_are_annotated():
    from dimenet.runtime.rectify.rectifier import Rectifier

    for method in (Rectifier.load, Rectifier.rectify, Rectifier.rectify_batch, Rectifier.network):
        signature = inspect.signature(method)
        missing = [n for n, p in signature.parameters.items() if n not in ("self", "cls") and p.annotation is p.empty]
        assert not missing and signature.return_annotation is not signature.empty, (method.__name__, missing)
