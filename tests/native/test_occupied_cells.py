"""The occupied cells of a frame's grid feature in the compiled core (``dimenet_occupied_cells``) against the
uncertainty's numpy count (``rectify.uncertainty.occupied_cells``): the same count on random sparse grids
with NaNs and negative zeros, and on the bench frames' features; refusals of bad arguments."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime import native
from dimenet.runtime.bench.latency import bench_frames, bench_rectifier
from dimenet.runtime.rectify import stages
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.uncertainty import occupied_cells

pytestmark = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")


def core():
    return native._compiled()[0]


def test_the_same_count_on_random_grids():
    rng = np.random.default_rng(8)
    for _ in range(500):
        channels, cells = int(rng.integers(1, 6)), int(rng.integers(1, 80))
        grid = rng.normal(size=cells * channels) * (rng.random(cells * channels) < rng.uniform(0.0, 0.5))
        grid[rng.random(grid.size) < 0.05] = -0.0
        if rng.random() < 0.3:
            grid[rng.integers(grid.size)] = np.nan  # numpy's any() counts a NaN as set
        assert core().occupied_cells(grid, channels) == occupied_cells(grid[None], channels)[0]


def test_the_same_count_on_the_bench_frames_features():
    rect = bench_rectifier(load_model("default"), "map")
    cam, features = rect._cam, rect._cam.spec.features
    p2, p3 = bench_frames(50, 60, rect.image_size, seed=3)  # 60 points: some cells stay empty
    counts = []
    for x, X in zip(p2, p3):
        feats, _ = stages.frame_features(cam, x, X, *stages.pnp(x, X, cam.K_c))
        grid = feats[0, : features.grid_size]
        counts.append(core().occupied_cells(grid, len(features.channels)))
        assert counts[-1] == occupied_cells(grid[None], len(features.channels))[0]
    assert min(counts) < features.grid_size // len(features.channels)  # empty cells were counted out


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="dividing"):
        core().occupied_cells(np.zeros(10), 3)
    with pytest.raises(ValueError, match="dividing"):
        core().occupied_cells(np.zeros(10), 0)
    with pytest.raises(TypeError, match="grid"):
        core().occupied_cells(np.zeros(10, np.float32), 2)
    with pytest.raises(TypeError, match="2 arguments"):
        core().occupied_cells(np.zeros(10))
