"""Plain helpers shared by the test modules (fixtures live in conftest.py).

``K_TEST`` and ``random_frames``: small synthetic scenes (no simulator needed). ``model_spec``,
``random_torch_model`` and ``random_model_file``: a random-init DimeNet exported to ONNX (needs
torch and onnx, else the calling test is skipped). ``constant_uncertainty`` and
``point_thickness``: uncertainty-model helpers. ``importable``: whether modules can be imported.
``DEVICE_MODEL``: the bundled default before the generic one (a galaxy-s8 device model, spec 1.4),
kept so device models and their spec are tested without torch. ``default_rectifier``: the
bundled (generic) model serving the example frames' camera.
"""

from __future__ import annotations

import os
from importlib import import_module, resources
from pathlib import Path

import numpy as np
import pytest

from dimenet.runtime import geometry as g
from dimenet.runtime.geometry import covariance_invariants, k_matrix, k_params
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.uncertainty import Uncertainty, thickness

DEVICE_MODEL = Path(__file__).parent / "data" / "device_model_galaxy_s8.onnx"


def example_camera():
    """The bundled example frames' camera (runtime/assets/example_camera.json)."""
    from dimenet.runtime.assets import asset
    from dimenet.runtime.formats.camera_file import read_camera

    with resources.as_file(asset("example_camera.json")) as path:
        return read_camera(path)


def default_rectifier(mode: str = "dimenet"):
    """The bundled default model serving the example camera (galaxy-s8 4032x3024)."""
    from dimenet.runtime.rectify.rectifier import Rectifier

    camera = example_camera()
    return Rectifier.load(K_c=camera.K, image_size=camera.image_size, mode=mode)


K_TEST = np.array([[3000.0, 0.0, 2016.0], [0.0, 3010.0, 1512.0], [0.0, 0.0, 1.0]])


def random_frames(rng, frames=4, points=60, noise_px=0.0, K=K_TEST, planar=False):
    """Non-planar point clouds ~0.4-0.9 m in front of a camera; returns p2 (px), p3 (mm), K, rvec, tvec."""
    X = rng.uniform(-150, 150, (frames, points, 3))
    if planar:
        X[..., 2] = 0.0
    K = np.broadcast_to(K, (frames, 3, 3)).copy()
    rvec = rng.normal(0, 0.2, (frames, 3))
    tvec = np.c_[rng.normal(0, 30, (frames, 2)), rng.uniform(400, 900, frames)]
    x = g.project(X, K, rvec, tvec) + rng.normal(0, noise_px, (frames, points, 2))
    return x, X, K, rvec, tvec


def importable(*names) -> bool:
    try:
        for name in names:
            import_module(name)
    except ImportError:
        return False
    return True


def model_spec(dataset, *, bounds_margin: float = 1.0) -> ModelSpec:
    """A spec for a simulated dataset: K_c the mean true K of its train frames, K_bounds their
    range widened by bounds_margin times its span on each side (as training does with K*)."""
    p = k_params(dataset.K_true[dataset.frames_in("train")])
    span = p.max(0) - p.min(0)
    bounds = np.stack([p.min(0) - bounds_margin * span, p.max(0) + bounds_margin * span], -1)
    return ModelSpec(
        features=FeatureSpec(),
        K_c=k_matrix(p.mean(0)),
        image_size=tuple(int(v) for v in dataset.image_size),
        K_bounds=bounds,
        hidden=(256, 128),
        provenance={"note": "random-init test model"},
    )


def random_torch_model(spec: ModelSpec, *, seed: int = 0, weight_scale: float = 1.0):
    torch = pytest.importorskip("torch")
    from dimenet.training.model import DimeNet

    torch.manual_seed(seed)
    model = DimeNet(spec.features.size, spec.hidden).eval()
    with torch.no_grad():
        model.fc3.weight.mul_(weight_scale)
    return model


def random_model_file(path, spec: ModelSpec, *, seed: int = 0, weight_scale: float = 1.0):
    """Export a random-init DimeNet (last layer scaled by weight_scale) to ``path``."""
    pytest.importorskip("onnx")
    from dimenet.export.onnx_export import export_model

    path.write_bytes(export_model(random_torch_model(spec, seed=seed, weight_scale=weight_scale), spec))
    return path


def constant_uncertainty(sigma_px: float) -> Uncertainty:
    coef = np.zeros((4, 5))
    coef[:, 0] = np.log(sigma_px)
    return Uncertainty(coef=coef, correlation=np.eye(4))


def point_thickness(points_3d: np.ndarray) -> float:
    return thickness(*covariance_invariants(np.ascontiguousarray(points_3d, dtype=np.float64)))


def pid_slow_here(seconds: float) -> int:
    """This process's id, after ``seconds`` of sleep when it is not a child process (a job ``jobs.workers.run_shared``
    runs here takes that long, one a helper runs none)."""
    import multiprocessing
    import time

    if multiprocessing.parent_process() is None:
        time.sleep(seconds)
    return os.getpid()


def assert_json_close(actual, expected, *, rtol: float = 1e-9, atol: float = 1e-9, where: str = "") -> None:
    """Two parsed JSON trees equal, their floats within rtol / atol: what the simulator and the
    runtime give varies in the last bits from run to run, the structure, strings, integers and
    booleans do not."""
    if isinstance(expected, dict):
        assert isinstance(actual, dict) and actual.keys() == expected.keys(), where
        for key in expected:
            assert_json_close(actual[key], expected[key], rtol=rtol, atol=atol, where=f"{where}.{key}")
    elif isinstance(expected, list):
        assert isinstance(actual, list) and len(actual) == len(expected), where
        for i, (a, e) in enumerate(zip(actual, expected)):
            assert_json_close(a, e, rtol=rtol, atol=atol, where=f"{where}[{i}]")
    elif isinstance(expected, float):
        assert isinstance(actual, (int, float)) and not isinstance(actual, bool), where
        assert abs(actual - expected) <= atol + rtol * abs(expected), f"{where}: {actual} != {expected}"
    else:
        assert actual == expected and type(actual) is type(expected), where
