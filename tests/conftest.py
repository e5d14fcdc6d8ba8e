"""Shared session fixtures: simulated datasets and their calibration, built once per test run.

``simulated(profile, seed)`` -> (Dataset, Calibration) for any device profile and seed: the
profile's rig frames (paper Table 1 splits) plus NATURAL_FRAMES natural-scene test frames,
calibrated with the real per-frame K* fit (K_c from the train frames). ``s8_dataset`` and
``s8_calibration`` are the default Galaxy S8 set (seed 0), the one most tests use.
"""

from __future__ import annotations

import os

# The batched LM solves thousands of tiny systems; OpenBLAS threads only contend for the cores
# (a 1.3 s calibration took 20+ s on a busy 2-core machine). Must be set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest

from dimenet.runtime.evaluation.calibration import calibrate_dataset
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
