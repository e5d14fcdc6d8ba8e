"""The torch-free runtime: Rectifier.rectify / rectify_batch, its input checks and fallbacks.

The model (conftest.py's ``model_path``) is a random-init DimeNet exported to ONNX (needs torch and
onnx), else the bundled default model; without either the tests are skipped. `dimenet rectify`:
tests/cli/test_rectify_command.py.
"""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from helpers import default_rectifier, model_spec, random_model_file

from dimenet.runtime.errors import InputError, ModelError
from dimenet.runtime.evaluation.metrics import reprojection_error_under_k
from dimenet.runtime.geometry import check_not_degenerate, covariance_invariants, k_matrix, k_params
from dimenet.runtime.rectify import checks
from dimenet.runtime.rectify import model as model_module
from dimenet.runtime.rectify.features import grid_features
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera


@pytest.fixture(scope="module")
def rectifier(model_path):
    return Rectifier.load(model_path) if model_path is not None else default_rectifier()


def frame_points(frames, b):
    m = frames.valid[b]
    return frames.points_2d[b][m], frames.points_3d[b][m]


def stub_rectifier(spec, delta_k):
    """A Rectifier whose model answers a constant Delta K (px) for every frame."""
    batch = lambda f: np.tile(np.asarray(delta_k, np.float32), (len(f), 1))  # noqa: E731
    return Rectifier(
        SimpleNamespace(
            spec=spec, delta_k=batch, frame_delta_k=lambda f: batch(f)[0].astype(np.float64), source="stub model"
        )
    )


def test_rectify_error_is_the_evaluation_metric(rectifier, frames):
    test = np.flatnonzero(frames.frames_in("test") & (frames.scene == "rig"))[:8]
    results = [rectifier.rectify(*frame_points(frames, b), refine=True) for b in test]
    K = np.array([r.K for r in results])
    p2, p3, valid = frames.points_2d[test], frames.points_3d[test], frames.valid[test]
    e = reprojection_error_under_k(p2, p3, valid, K)
    e_c = reprojection_error_under_k(p2, p3, valid, rectifier.K_c)
    np.testing.assert_allclose([r.reprojection_error_px for r in results], e, atol=1e-3)
    np.testing.assert_allclose([r.reprojection_error_kc_px for r in results], e_c, atol=1e-3)
    for r in results:
        assert r.K.shape == (3, 3) and r.rvec.shape == r.tvec.shape == (3,) and r.delta_k.shape == (4,)
        np.testing.assert_allclose(r.K, k_matrix(k_params(rectifier.K_c) + r.delta_k), rtol=1e-15, atol=1e-9)
        assert set(r.timings_us) == {"validate", "pnp_kc", "features", "model", "pnp_k", "refine", "check"}


def test_batch_equals_per_frame(rectifier, frames):
    idx = np.flatnonzero(frames.scene == "rig")[:6]
    batch = rectifier.rectify_batch(frames.points_2d[idx], frames.points_3d[idx], frames.valid[idx])
    single = [rectifier.rectify(*frame_points(frames, b)) for b in idx]
    np.testing.assert_allclose(batch.K, [s.K for s in single], atol=1e-4)
    np.testing.assert_allclose(batch.delta_k, [s.delta_k for s in single], atol=1e-4)
    np.testing.assert_allclose(batch.rvec, [s.rvec for s in single], atol=1e-6)
    np.testing.assert_allclose(batch.tvec, [s.tvec for s in single], atol=1e-4)
    np.testing.assert_allclose(batch.reprojection_error_px, [s.reprojection_error_px for s in single], atol=1e-6)
    np.testing.assert_allclose(batch.reprojection_error_kc_px, [s.reprojection_error_kc_px for s in single], atol=1e-6)
    assert batch.fallback == tuple(s.fallback for s in single)


def test_frame_delta_k_is_the_batch_call_in_every_thread(rectifier, frames):
    from concurrent.futures import ThreadPoolExecutor

    spec = rectifier.spec.for_camera(Camera(rectifier.K_c, rectifier.image_size)).model  # a generic one: canonical
    feats = grid_features(
        frames.points_2d, frames.points_3d, frames.infer_mask, spec.K_c, spec.image_size, spec.features
    )
    expected = rectifier.model.delta_k(feats.astype(np.float32)).astype(np.float64)
    # The IO binding's buffers are per thread: concurrent calls must not see each other's frames.
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda f: rectifier.model.frame_delta_k(f[None]), list(feats) * 8))
    np.testing.assert_array_equal(np.array(got), np.tile(expected, (8, 1)))
    assert got[0].dtype == np.float64 and got[0].shape == (4,)


@pytest.mark.parametrize("which", ["test model", "bundled default"])
def test_batch_infers_k_from_the_infer_mask(which, rectifier, frames):
    # The bundled default reads a data step, whose Gauss-Newton Hessian a refused frame (no inference point) has not.
    rectifier = rectifier if which == "test model" else default_rectifier()
    idx = np.flatnonzero(frames.scene == "natural")
    p2, p3, valid, infer = frames.points_2d[idx], frames.points_3d[idx], frames.valid[idx], frames.infer_mask[idx]
    assert np.all(infer.sum(1) < valid.sum(1))
    few = infer.copy()
    few[0, np.flatnonzero(few[0])[3:]] = False
    res = rectifier.rectify_batch(p2, p3, valid, infer_mask=few)
    assert res.fallback[0].startswith("no K inferred: 3 inference points")
    assert res.fallback_code[0] == "no_k_inferred" and res.fallback[0].refusal
    np.testing.assert_array_equal(res.K[0], rectifier.K_c)
    full = rectifier.rectify_batch(p2, p3, valid, infer_mask=infer, refine=True)
    np.testing.assert_allclose(res.K[1:], full.K[1:], atol=1e-9)
    # poses and errors use all valid points
    K_c = rectifier.K_c
    np.testing.assert_allclose(full.reprojection_error_kc_px, reprojection_error_under_k(p2, p3, valid, K_c), atol=1e-3)
    np.testing.assert_allclose(full.reprojection_error_px, reprojection_error_under_k(p2, p3, valid, full.K), atol=1e-3)
    with pytest.raises(InputError, match="infer_mask: must be a subset of valid"):
        rectifier.rectify_batch(p2, p3, infer, infer_mask=valid)


def test_lists_and_float32_are_cast(rectifier, frames):
    p2, p3 = frame_points(frames, 0)
    ref = rectifier.rectify(p2, p3)
    as_list = rectifier.rectify(p2.tolist(), p3.tolist())
    np.testing.assert_array_equal(as_list.K, ref.K)
    as_f32 = rectifier.rectify(p2.astype(np.float32), p3.astype(np.float32))
    np.testing.assert_allclose(as_f32.K, ref.K, atol=0.05)


def _collinear(p2, p3):
    t = np.linspace(0.0, 1.0, len(p3))[:, None]
    return p2, np.array([10.0, 20.0, 30.0]) + t * np.array([100.0, 50.0, 20.0])


BAD_INPUTS = {
    "points_2d: expected shape \\(N, 2\\)": lambda p2, p3: (p2[:, :1], p3),
    "points_3d: expected shape \\(N, 3\\)": lambda p2, p3: (p2, p3[None]),
    "points_2d: dtype <U.* cannot be cast": lambda p2, p3: (p2.astype(str), p3),
    "points_3d: dtype complex128 cannot be cast": lambda p2, p3: (p2, p3.astype(complex)),
    "points_2d: not an array of numbers": lambda p2, p3: ([[1.0, 2.0], [3.0]] + p2.tolist(), p3),
    "5 points: rectification needs at least 6": lambda p2, p3: (p2[:5], p3[:5]),
    "points_2d has .* points and points_3d .*: they must correspond": lambda p2, p3: (p2[:-1], p3),
    "points_2d: point 3 is not finite": lambda p2, p3: (np.where(np.arange(len(p2))[:, None] == 3, np.nan, p2), p3),
    "points_3d: point 0 is not finite": lambda p2, p3: (p2, np.where(np.arange(len(p3))[:, None] == 0, np.inf, p3)),
    "point 2 at \\(5000.0, .*outside the camera.s 4032x3024 px image": lambda p2, p3: (
        np.where(np.arange(len(p2))[:, None] == 2, [5000.0, 100.0], p2),
        p3,
    ),
    "point 1 at \\(-3.0, .*outside": lambda p2, p3: (np.where(np.arange(len(p2))[:, None] == 1, [-3.0, 100.0], p2), p3),
    "points_3d: all points are collinear": _collinear,
    "points_2d: all points coincide": lambda p2, p3: (np.broadcast_to([1000.0, 800.0], p2.shape), p3),
}


@pytest.mark.parametrize("message", list(BAD_INPUTS))
def test_bad_input_is_an_input_error_naming_the_problem(rectifier, frames, message):
    p2, p3 = BAD_INPUTS[message](*frame_points(frames, 0))
    with pytest.raises(InputError, match=message):
        rectifier.rectify(p2, p3)


def test_spread_tests_of_one_frame_and_of_a_batch_agree_and_imply_the_exact_check():
    """The cheap spread test (single frame: OpenCV covariance; batch: numpy) decides the same
    frames, and every frame it passes also passes check_not_degenerate."""
    rng = np.random.default_rng(3)
    base = rng.normal(size=(40, 3)) * [300.0, 200.0, 100.0] + [0.0, 0.0, 600.0]
    direction = np.array([1.0, 0.5, 0.2])
    frames = [
        base,
        base * [1.0, 1.0, 0.0],  # spread; planar (still spread over 2 dimensions)
        np.linspace(0, 1, 40)[:, None] * direction * 500 + rng.normal(size=(40, 3)) * 1e-3,  # nearly collinear
        np.outer(np.linspace(0, 1, 40), direction) * 500,  # collinear
        np.broadcast_to([5.0, 6.0, 7.0], (40, 3)) + rng.normal(size=(40, 3)) * 1e-12,
    ]  # coincident
    points = np.stack(frames)
    passed = np.ones(len(points), bool)
    for D in (3, 2):
        batch = checks.spread_frames(points[..., :D], None)[0]
        single = [checks.well_spread(f, covariance_invariants(f)) for f in map(np.ascontiguousarray, points[..., :D])]
        assert batch.tolist() == single
        assert single[:2] == [True, True] and single[3:] == [False, False]
        passed &= single
    for f in points[passed]:
        check_not_degenerate(f[:, :2], f)  # raises when the cheap test was wrong


def test_bad_frames_of_a_batch_are_named(rectifier, frames, monkeypatch):
    p2, p3, valid = frames.points_2d[:3].copy(), frames.points_3d[:3].copy(), frames.valid[:3]
    first = int(np.argmax(valid[1] & (np.arange(valid.shape[1]) > 10)))
    p2[1, first] = np.nan
    with pytest.raises(InputError, match=f"frame 1: points_2d: point {first} is not finite"):
        rectifier.rectify_batch(p2, p3, valid)
    few = valid.copy()
    few[2, np.flatnonzero(few[2])[5:]] = False
    with pytest.raises(InputError, match="frame 2: 5 valid points"):
        rectifier.rectify_batch(frames.points_2d[:3], p3, few)
    with pytest.raises(InputError, match="valid: expected a bool array of shape \\(3, "):
        rectifier.rectify_batch(frames.points_2d[:3], p3, valid[:2])
    monkeypatch.setattr("dimenet.runtime.geometry.pnp.cv2.solvePnP", lambda *a, **k: (False, np.zeros(3), np.zeros(3)))
    with pytest.raises(InputError, match="frame 0: PnP failed"):
        rectifier.rectify_batch(frames.points_2d[:3], p3, valid)
    with pytest.raises(InputError, match="PnP failed"):
        rectifier.rectify(*frame_points(frames, 0))


def _assert_kc_solution(res, spec, reason, code):
    assert res.fallback is not None and reason in res.fallback and res.fallback_code == code
    np.testing.assert_array_equal(res.K, spec.K_c)
    np.testing.assert_array_equal(res.delta_k, np.zeros(4))
    assert res.reprojection_error_px == res.reprojection_error_kc_px
    assert np.all(np.isfinite(res.rvec)) and np.all(np.isfinite(res.tvec)) and np.isfinite(res.reprojection_error_px)


def test_implausible_k_from_huge_weights_falls_back_to_k_c(tmp_path, frames):
    spec = model_spec(frames)
    huge = Rectifier.load(random_model_file(tmp_path / "huge.onnx", spec, weight_scale=1e4))
    p2, p3 = frame_points(frames, 0)
    res = huge.rectify(p2, p3)
    _assert_kc_solution(res, spec, "outside the model's K_bounds", "implausible")
    _, rvec_c, _ = cv2.solvePnP(p3, p2, spec.K_c, None, flags=cv2.SOLVEPNP_SQPNP)
    np.testing.assert_allclose(res.rvec, rvec_c.ravel(), atol=1e-12)
    batch = huge.rectify_batch(frames.points_2d[:2], frames.points_3d[:2], frames.valid[:2])
    assert all("K_bounds" in r for r in batch.fallback) and np.all(batch.K == spec.K_c)
    assert batch.fallback_code == ("implausible", "implausible")


@pytest.mark.parametrize(
    "delta_k, reason, code",
    [
        ([np.nan, 0.0, 0.0, 0.0], "Delta K is not finite", "implausible"),
        ([0.0, 0.0, 400.0, -300.0], "fits worse than K_c", "worse_than_k_c"),
    ],
)
def test_non_finite_or_worse_k_falls_back_to_k_c(frames, delta_k, reason, code):
    spec = replace(model_spec(frames), K_bounds=np.array([[0.0, 1e4]] * 4))
    stub = stub_rectifier(spec, delta_k)
    p2, p3 = frame_points(frames, 0)
    _assert_kc_solution(stub.rectify(p2, p3), spec, reason, code)
    _assert_kc_solution(stub.rectify(p2, p3, refine=True), spec, reason, code)
    batch = stub.rectify_batch(frames.points_2d[:2], frames.points_3d[:2], frames.valid[:2])
    assert all(reason in r for r in batch.fallback) and np.all(np.isfinite(batch.reprojection_error_px))
    assert batch.fallback_code == (code, code)


@pytest.mark.parametrize("name", ["default", "paper-rig"])
def test_missing_bundled_model_is_a_model_error(monkeypatch, name):
    monkeypatch.setitem(model_module.BUNDLED_MODELS, name, "absent_model.onnx")
    with pytest.raises(ModelError, match=f"no bundled {name} model"):
        Rectifier.load(None if name == "default" else name, K_c=np.diag([3000.0, 3000.0, 1.0]), image_size=(4000, 3000))
