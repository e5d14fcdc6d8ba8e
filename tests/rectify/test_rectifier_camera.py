"""The rectifier serving the user's camera: a generic model is scale free (resolution, world
unit), a device model serves rescales of its camera, the K_c used is reported, and frames that
do not fit the camera fall back with a reason."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import constant_uncertainty, example_camera, model_spec
from test_pixel_map import generic_spec, half

from dimenet.runtime.errors import CameraError
from dimenet.runtime.geometry import k_params
from dimenet.runtime.rectify.rectifier import Rectifier, _camera
from dimenet.runtime.rectify.user_camera import Camera


def linear_model(spec, seed=0, scale=0.02):
    """A stand-in network: Delta K = features @ W (model px), deterministic and input-dependent."""
    W = np.random.default_rng(seed).normal(0.0, scale, (spec.features.size, 4))

    def batch(f):
        return (np.asarray(f, np.float64) @ W).astype(np.float32)

    return SimpleNamespace(
        spec=spec, delta_k=batch, frame_delta_k=lambda f: batch(f)[0].astype(np.float64), source="linear.onnx"
    )


def rig_frames(frames):
    test = np.flatnonzero(frames.scene == "rig")[:12]
    return frames.points_2d[test], frames.points_3d[test], frames.valid[test]


def to_half(points_2d):
    return (points_2d + 0.5) / 2 - 0.5


def up(k):
    """(..., 4) half-resolution (fx, fy, cx, cy) -> full resolution."""
    k = np.array(k, dtype=np.float64)
    k[..., :2] *= 2
    k[..., 2:] = (k[..., 2:] + 0.5) * 2 - 0.5
    return k


@pytest.fixture(scope="module")
def K_c(frames):
    return model_spec(frames).K_c


@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_a_generic_model_is_free_of_resolution_and_world_unit(frames, K_c, mode, without_evidence_rule):
    spec = replace(generic_spec(), uncertainty=constant_uncertainty(3.0))
    model = linear_model(spec)
    full = Rectifier(model, mode, Camera(K_c, (4032, 3024)))
    halved = Rectifier(model, mode, Camera(half(K_c), (2016, 1512)))
    p2, p3, valid = rig_frames(frames)
    rf = full.rectify_batch(p2, p3, valid)
    # the stand-in network moves K; a frame its K fits worse than K_c keeps K_c, in both cameras alike
    assert sum(f is None for f in rf.fallback) >= len(rf.fallback) // 2 and np.abs(rf.delta_k).max() > 0.1
    rh = halved.rectify_batch(np.where(valid[..., None], to_half(p2), 0.0), p3, valid)
    np.testing.assert_allclose(up(k_params(rh.K)), k_params(rf.K), atol=1e-6)
    np.testing.assert_allclose(2 * rh.reprojection_error_px, rf.reprojection_error_px, rtol=1e-6)
    np.testing.assert_allclose(4 * rh.K_cov, rf.K_cov, rtol=1e-6)
    rm = full.rectify_batch(p2, p3 / 1000.0, valid)  # metres
    np.testing.assert_allclose(k_params(rm.K), k_params(rf.K), atol=1e-6)
    np.testing.assert_allclose(rm.tvec * 1000.0, rf.tvec, rtol=1e-6)
    # One frame at a time gives the batch's result; the K_c used is the camera's.
    for b in range(3):
        m = valid[b]
        one = halved.rectify(to_half(p2[b][m]), p3[b][m])
        np.testing.assert_allclose(one.K, rh.K[b], atol=1e-6)
        np.testing.assert_array_equal(one.K_c, half(K_c))
    np.testing.assert_array_equal(rh.K_c, half(K_c))


def test_a_device_model_serves_a_rescale_of_its_camera(frames):
    spec = model_spec(frames)
    model = linear_model(spec, scale=0.01)
    p2, p3, valid = rig_frames(frames)
    rf = Rectifier(model).rectify_batch(p2, p3, valid)
    halved = Rectifier(model, "dimenet", _camera(model, None, (2016, 1512)))
    np.testing.assert_allclose(halved.K_c, half(spec.K_c), atol=1e-9)
    rh = halved.rectify_batch(np.where(valid[..., None], to_half(p2), 0.0), p3, valid)
    np.testing.assert_allclose(up(k_params(rh.K)), k_params(rf.K), atol=1e-6)
    assert [f is None for f in rh.fallback] == [f is None for f in rf.fallback]  # the reasons' px are each camera's


def test_a_generic_model_needs_the_camera_named(frames):
    model = linear_model(generic_spec())
    with pytest.raises(CameraError, match="generic model: it needs your camera"):
        Rectifier(model)
    with pytest.raises(CameraError, match="needs both K_c .* got only image_size"):
        _camera(model, None, (4032, 3024))


def test_half_resolution_points_under_a_full_resolution_k_c_never_get_a_silent_k(frames, K_c):
    """Points of another resolution fit K_c only with a large error that no OIS K removes: they
    fall back (the range or the mismatch rule), whatever the network says."""
    p2, p3, valid = rig_frames(frames)
    for seed in range(3):
        rect = Rectifier(linear_model(generic_spec(), seed=seed), "dimenet", Camera(K_c, (4032, 3024)))
        res = rect.rectify_batch(np.where(valid[..., None], to_half(p2), 0.0), p3, valid)
        assert all(res.fallback), res.fallback
        assert all(("K_c" in r) or ("camera" in r) for r in res.fallback)
        assert set(res.fallback_code) <= {"out_of_range", "mismatch", "worse_than_k_c"}
        np.testing.assert_array_equal(res.K, np.broadcast_to(K_c, res.K.shape))


def test_the_bundled_generic_model_serves_any_resolution_and_refuses_a_mismatched_one(frames):
    """The bundled default: the camera is required; half resolution gives K/2 and metres the
    millimetres' K; half-resolution points under the full-resolution K_c never get a K."""
    with pytest.raises(CameraError, match="generic model"):
        Rectifier.load()
    camera = example_camera()
    full = Rectifier.load(K_c=camera.K, image_size=camera.image_size)
    halved = Rectifier.load(K_c=half(camera.K), image_size=(2016, 1512))
    p2, p3, valid = rig_frames(frames)
    rf = full.rectify_batch(p2, p3, valid)
    assert not any(rf.fallback)
    rh = halved.rectify_batch(np.where(valid[..., None], to_half(p2), 0.0), p3, valid)
    assert np.abs(up(k_params(rh.K)) - k_params(rf.K)).mean() < 1e-6
    assert np.abs(k_params(full.rectify_batch(p2, p3 / 1000.0, valid).K) - k_params(rf.K)).max() < 1e-6
    mismatched = full.rectify_batch(np.where(valid[..., None], to_half(p2), 0.0), p3, valid)
    assert all(mismatched.fallback)
