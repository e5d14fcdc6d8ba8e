"""The registry of encoders (``rectify.encoders``): every encoder once, its size the span of the feature it
fills, its numpy reference those inputs; a new encoder needs its module and a registry entry."""

from types import SimpleNamespace

import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import native
from dimenet.runtime.geometry import monomial_gram
from dimenet.runtime.rectify import encoders
from dimenet.runtime.rectify.encoders import ENCODERS, grid, spans
from dimenet.runtime.rectify.features import FeatureSpec, grid_features
from dimenet.runtime.rectify.grid import Grid

IMAGE = (4032, 3024)
SPECS = [
    FeatureSpec(),
    FeatureSpec(grid=Grid(7, 5), variant="C", depth_mm=500.0),
    FeatureSpec(data_step=True),
    FeatureSpec(grid=Grid(1, 1), variant="B", moments=True, depth_mm=300.0),
    FeatureSpec(grid=Grid(8, 6), depth_mm=500.0, data_step=True, moments=True),  # any-scene's
]


def test_the_registry_lists_each_encoder_once_grid_first():
    assert list(ENCODERS) == ["grid", "data_step", "moments"]
    assert all(name == module.NAME for name, module in ENCODERS.items())


@pytest.mark.parametrize("implementation", native.IMPLEMENTATIONS)
@pytest.mark.parametrize("spec", SPECS, ids=str)
def test_each_encoder_fills_its_span_with_its_reference(spec, implementation):
    if implementation == "c" and native._compiled()[0] is None:
        pytest.skip("the compiled core is not built")
    x, X, _, rvec, tvec = random_frames(np.random.default_rng(3), frames=3, points=80, noise_px=0.5)
    with native.using(implementation):
        feats, points = grid_features(x, X, None, K_TEST, IMAGE, spec, poses=(rvec, tvec), return_points=True)
    assert feats.shape == (3, spec.size) == (3, sum(module.size(spec) for module in ENCODERS.values()))
    parts = spans(spec)
    assert parts["grid"] == slice(0, spec.grid_size) and max(s.stop for s in parts.values()) == spec.size
    for b in range(3):
        G = monomial_gram(points[b, 2:5], points[b, :2])
        for name, module in ENCODERS.items():
            if name == grid.NAME or not module.size(spec):
                continue
            np.testing.assert_allclose(feats[b, parts[name]], module.encode(G, 80, K_TEST, spec), rtol=0, atol=1e-12)


def test_a_new_encoder_is_its_module_and_a_registry_entry(monkeypatch):
    """A toy encoder, each frame's point count, registered here alone: the numpy feature grows by it."""
    count = SimpleNamespace(NAME="count", size=lambda spec: 1, encode=lambda G, n, K_c, spec: [float(n)])
    spec = FeatureSpec(data_step=True)
    x, X, _, rvec, tvec = random_frames(np.random.default_rng(4), frames=2, points=50)
    with native.using("python"):
        before = grid_features(x, X, None, K_TEST, IMAGE, spec, poses=(rvec, tvec))
        monkeypatch.setitem(encoders.ENCODERS, "count", count)
        after = grid_features(x, X, None, K_TEST, IMAGE, spec, poses=(rvec, tvec))
    assert spec.size == before.shape[1] + 1 and spans(spec)["count"] == slice(before.shape[1], spec.size)
    np.testing.assert_array_equal(after[:, :-1], before)
    np.testing.assert_array_equal(after[:, -1], [50.0, 50.0])
