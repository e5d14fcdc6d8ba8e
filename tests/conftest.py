"""Shared session fixtures: simulated datasets and their calibration, built once per test run.

``simulated(profile, seed)`` -> (Dataset, Calibration) for any device profile and seed: the
profile's rig frames (paper Table 1 splits) plus NATURAL_FRAMES natural-scene test frames,
calibrated with the real per-frame K* fit (K_c from the train frames). ``s8_dataset`` and
``s8_calibration`` are the default Galaxy S8 set (seed 0), the one most tests use.

``frames`` (simulated Galaxy S8 frames, seed 7) and ``model_path`` (a random-init model exported for
them, else None: the bundled default model) serve the rectifier, `dimenet rectify` and `dimenet bench`
tests; ``map_model`` (frames with planar ones, and a random-init model with a constant uncertainty
model) serves the MAP-mode, `dimenet evaluate --methods` and `dimenet bench --mode map` tests.
Plain helper functions live in helpers.py (``from helpers import ...``: pytest's prepend import mode
puts this folder on sys.path when it loads this conftest).
"""

from __future__ import annotations

import os

# The batched LM solves thousands of tiny systems; OpenBLAS threads only contend for the cores
# (a 1.3 s calibration took 20+ s on a busy 2-core machine). Must be set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from dataclasses import replace

import pytest
from helpers import constant_uncertainty, importable, model_spec, random_model_file

from dimenet.runtime.assets import asset
from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.rectify import model as model_module
from dimenet.runtime.sim.simulator import simulate

NATURAL_FRAMES = 34  # the paper's LEGO test set size


@pytest.fixture(scope="session")
def simulated():
    cache = {}

    def get(profile: str, seed: int = 0):
        if (profile, seed) not in cache:
            ds = simulate(profile, seed=seed, natural_frames=NATURAL_FRAMES)
            cache[profile, seed] = (ds, calibrate_dataset(ds))
        return cache[profile, seed]

    return get


@pytest.fixture(scope="session")
def s8_dataset(simulated):
    return simulated("galaxy-s8", 0)[0]


@pytest.fixture(scope="session")
def s8_calibration(simulated):
    return simulated("galaxy-s8", 0)[1]


@pytest.fixture(scope="session")
def frames():
    """Simulated galaxy-s8 frames: rig frames (NaN-padded) and natural frames (infer_mask < valid)."""
    return simulate("galaxy-s8", seed=7, natural_frames=3)


@pytest.fixture(scope="session")
def model_path(tmp_path_factory, frames):
    """A random-init model exported for these frames, else None (the bundled default model)."""
    if importable("torch", "onnx"):
        return random_model_file(tmp_path_factory.mktemp("model") / "random.onnx", model_spec(frames))
    if not asset(model_module.DEFAULT_MODEL).is_file():
        pytest.skip("needs torch and onnx to export a test model, or the bundled default model")
    return None


@pytest.fixture(scope="session")
def map_model(tmp_path_factory):
    frames = simulate("galaxy-s8", seed=7, natural_frames=2, planar_frames=2)
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(8.0))
    return frames, random_model_file(tmp_path_factory.mktemp("map") / "map.onnx", spec)


@pytest.fixture
def without_evidence_rule(monkeypatch):
    """The evidence rule off (``rectify.checks.EVIDENCE_P`` 1: no p-value is above it), for tests whose stand-in
    networks move K at random: the rule keeps K_c on nearly every frame of theirs, and the path under test would
    not run."""
    from dimenet.runtime.rectify import checks

    monkeypatch.setattr(checks, "EVIDENCE_P", 1.0)
