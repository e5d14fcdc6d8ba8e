"""The compiled core against the numpy reference (issue 49): the feature of every encoder, e_c, the
errors, and ``Rectifier.rectify`` end to end, under both implementations in one process
(``native.using``).

The bar: features within 1e-12 absolute on the scaled features the model reads, K within 1e-9 px, rvec
and tvec within 1e-9 relative, the same fallbacks. The core follows the reference's order of operations,
so it meets it with nothing to spare: every figure here is 0 (bit-identical) on this machine. A frame
whose float32 feature flips (the model reads float32) would be counted and bounded instead
(``K_FLIP_BOUND_PX``); none does.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import native
from dimenet.runtime.bench.latency import bench_frames, bench_rectifier
from dimenet.runtime.errors import InputError
from dimenet.runtime.rectify import stages
from dimenet.runtime.rectify.checks import validated_frame
from dimenet.runtime.rectify.features import FeatureSpec, grid_features, poses_c0
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier

pytestmark = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")

GOLDEN_DIR = Path(__file__).resolve().parents[2] / "models_spec" / "golden"
GOLDEN = {"default": GOLDEN_DIR / "golden.json", "paper-rig": GOLDEN_DIR / "paper-rig" / "golden.json"}
FEATURE_TOL = 1e-12
K_TOL_PX = 1e-9
POSE_TOL_REL = 1e-9
K_FLIP_BOUND_PX = 2.0**-15  # the parity bound of a float32 flip (export.golden.PARITY_PX)
IMAGE = (4032, 3024)
BENCH_FRAMES = 2000


def both(function, *args, **kwargs):
    """function(*args, **kwargs) under the numpy reference, then under the compiled core."""
    out = {}
    for name in ("python", "c"):
        with native.using(name):
            out[name] = function(*args, **kwargs)
    return out["python"], out["c"]


def flips(a: np.ndarray, b: np.ndarray) -> int:
    """Features whose float32 rounding differs (what the model reads)."""
    return int(np.count_nonzero(a.astype(np.float32) != b.astype(np.float32)))


def assert_same_results(reference, compiled, where: str) -> tuple[float, int]:
    """rectify's results equal within the bar; -> (largest K difference px, fallbacks that differ)."""
    assert reference.fallback == compiled.fallback, where
    assert reference.fallback_code == compiled.fallback_code, where
    k_diff = float(np.abs(reference.K - compiled.K).max())
    assert k_diff <= K_TOL_PX, (where, k_diff)
    for a, b in ((reference.rvec, compiled.rvec), (reference.tvec, compiled.tvec)):
        assert np.abs(a - b).max() <= POSE_TOL_REL * max(1.0, np.abs(a).max()), where
    assert abs(reference.reprojection_error_px - compiled.reprojection_error_px) <= 1e-12, where
    assert abs(reference.reprojection_error_kc_px - compiled.reprojection_error_kc_px) <= 1e-12, where
    return k_diff, 0


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_frames_give_the_same_feature_e_c_and_rectification(name):
    golden = json.loads(GOLDEN[name].read_text())
    worst_feature, worst_k, flipped = 0.0, 0.0, 0
    for frame in golden["frames"]:
        x, want = frame["inputs"], frame["expected"]
        rect = Rectifier.load(name, K_c=np.array(x["K_c"]), image_size=tuple(int(v) for v in x["image_size"]))
        p2, p3 = np.array(x["points_2d"]), np.array(x["points_3d"])
        _, q2, q3, _ = validated_frame(rect._cam.image, rect._cam.to_model, p2, p3)
        pose = np.array(want["rvec"]), np.array(want["tvec"])
        (f_py, e_py), (f_c, e_c) = both(stages.frame_features, rect._cam, q2, q3, *pose)
        worst_feature = max(worst_feature, float(np.abs(f_py - f_c).max()))
        flipped += flips(f_py, f_c)
        assert abs(e_py - e_c) <= 1e-12 * e_py, frame["name"]
        reference, compiled = both(rect.rectify, p2, p3)
        worst_k = max(worst_k, assert_same_results(reference, compiled, frame["name"])[0])
        net_py, net_c = both(rect.network, p2, p3, *pose)
        assert np.abs(net_py.K - net_c.K).max() <= K_TOL_PX, frame["name"]
    assert worst_feature <= FEATURE_TOL and flipped == 0 and worst_k <= K_TOL_PX, (worst_feature, flipped, worst_k)


@pytest.fixture(scope="module")
def bench_set():
    """The bench's 2000 frames of 320 points (``dimenet bench``'s generator) and each model's rectifier."""
    rectifiers = {name: bench_rectifier(load_model(name), "dimenet") for name in sorted(GOLDEN)}
    p2, p3 = bench_frames(BENCH_FRAMES, 320, rectifiers["default"].image_size)
    return rectifiers, p2, p3


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_2000_bench_frames_give_the_same_features_and_rectifications(bench_set, name):
    rectifiers, p2, p3 = bench_set
    rect = rectifiers[name]
    cam = rect._cam
    poses = poses_c0(p2, p3, None, cam.K_c)
    spec = cam.spec.features
    reference, compiled = both(grid_features, p2, p3, None, cam.K_c, cam.spec.image_size, spec, poses=poses)
    assert np.abs(reference - compiled).max() <= FEATURE_TOL
    flipped = np.any(reference.astype(np.float32) != compiled.astype(np.float32), axis=1)
    results_py, results_c = both(lambda: [rect.rectify(x, X) for x, X in zip(p2, p3)])
    k_diffs = np.array([np.abs(a.K - b.K).max() for a, b in zip(results_py, results_c)])
    # A frame whose float32 feature flipped may move K by up to the parity bound; none does here.
    assert np.count_nonzero(flipped) <= BENCH_FRAMES // 100
    assert k_diffs[flipped].max(initial=0.0) <= K_FLIP_BOUND_PX
    for b in np.flatnonzero(~flipped):
        assert_same_results(results_py[b], results_c[b], f"bench frame {b}")


SPECS = [
    FeatureSpec(grid=Grid(8, 6), variant="A", depth_mm=500.0),  # the default's
    FeatureSpec(grid=Grid(8, 6), variant="A", depth_mm=500.0, data_step=True, moments=True),  # any-scene's
    *(FeatureSpec(grid=Grid(7, 5), variant=v) for v in "BCDE"),
    FeatureSpec(grid=Grid(1, 1), variant="C", depth_mm=300.0, moments=True),
    FeatureSpec(grid=Grid(3, 11), variant="D", data_step=True),
    FeatureSpec(grid=Grid(16, 12), variant="E", depth_mm=1000.0, data_step=True, moments=True),
]


@pytest.mark.parametrize("spec", SPECS, ids=str)
@pytest.mark.parametrize("kind", ["3d", "planar", "masked", "batch of 12"])
def test_every_encoder_gives_the_same_feature_and_point_rows(spec, kind):
    rng = np.random.default_rng(49)
    frames = 12 if kind == "batch of 12" else 3
    x, X, _, rvec, tvec = random_frames(rng, frames=frames, points=90, noise_px=1.5, planar=kind == "planar")
    mask = rng.random(x.shape[:2]) > 0.3 if kind == "masked" else None
    K_c = K_TEST.copy()
    K_c[0, 2] += 9.0

    (f_py, rows_py), (f_c, rows_c) = both(
        grid_features, x, X, mask, K_c, IMAGE, spec, poses=(rvec, tvec), return_points=True
    )
    assert f_py.shape == f_c.shape == (frames, spec.size)
    assert np.abs(f_py - f_c).max() <= FEATURE_TOL
    np.testing.assert_array_equal(rows_py, rows_c)


def test_masked_poses_solved_inside_grid_features_are_the_same():
    rng = np.random.default_rng(3)
    x, X, _, _, _ = random_frames(rng, frames=4, points=80, noise_px=1.0)
    mask = rng.random((4, 80)) > 0.25
    spec = SPECS[1]
    reference, compiled = both(grid_features, x, X, mask, K_TEST, IMAGE, spec)
    assert np.abs(reference - compiled).max() <= FEATURE_TOL


def _error(function, *args, **kwargs) -> str:
    with pytest.raises(InputError) as info:
        function(*args, **kwargs)
    return str(info.value)


def test_the_same_input_errors_with_the_same_messages():
    rng = np.random.default_rng(5)
    x, X, _, rvec, tvec = random_frames(rng, frames=1, points=40)
    spec = SPECS[1]
    same_point = np.repeat(x[:, :1], 40, axis=1), np.repeat(X[:, :1], 40, axis=1)
    nan_pixel = x.copy()
    nan_pixel[0, 3, 0] = np.nan
    for p2, p3 in (same_point, (nan_pixel, X)):
        messages = both(_error, grid_features, p2, p3, None, K_TEST, IMAGE, spec, poses=(rvec, tvec))
        assert messages[0] == messages[1] and messages[0].startswith("the points fix no pose"), messages
    # behind the camera: the hot path refuses it with the same count, grid_features computes it anyway
    cam = default_camera()
    behind = (-rvec[0], -tvec[0])
    messages = both(_error, stages.frame_features, cam, x[0], X[0], *behind)
    assert messages[0] == messages[1] and "lie behind the camera" in messages[0], messages
    reference, compiled = both(grid_features, x, X, None, K_TEST, IMAGE, SPECS[0], poses=(-rvec, -tvec))
    np.testing.assert_array_equal(reference, compiled)


def test_hostile_values_propagate_alike():
    """NaN and inf pixels (NaN to the first cell, inf to the edge), a huge point: the same features, NaN for
    NaN (the default's encoder: no data step to refuse them)."""
    rng = np.random.default_rng(11)
    x, X, _, rvec, tvec = random_frames(rng, frames=2, points=50)
    x[0, 0] = np.nan
    x[0, 1] = np.inf, -np.inf
    X[1, 2] = 1e300
    reference, compiled = both(grid_features, x, X, None, K_TEST, IMAGE, SPECS[0], poses=(rvec, tvec))
    np.testing.assert_array_equal(reference, compiled)


def default_camera() -> stages.ModelCamera:
    rect = Rectifier.load(K_c=K_TEST, image_size=IMAGE)
    return rect._cam
