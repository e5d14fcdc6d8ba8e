"""The camera at run time (rectify.user_camera and ModelSpec.for_camera): the pixel map between the
user's camera and the model's pixels, the device model's rescale-or-crop rule, and generic specs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import K_TEST

from dimenet.runtime.errors import CameraError, ModelError
from dimenet.runtime.geometry import k_matrix, k_params, project
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.spec import GenericCamera, ModelSpec
from dimenet.runtime.rectify.user_camera import (
    Camera,
    PixelMap,
    checked_camera,
    device_pixel_map,
    generic_pixel_map,
)

SIZE = (4032, 3024)


def half(K: np.ndarray) -> np.ndarray:
    """K of the same camera at half resolution (OpenCV: pixel centres at integers)."""
    k = k_params(K)
    return k_matrix(np.r_[k[:2] / 2, (k[2:] + 0.5) / 2 - 0.5])


def generic_spec() -> ModelSpec:
    return ModelSpec(
        features=FeatureSpec(depth_mm=500.0),
        K_c=None,
        image_size=None,
        K_bounds=None,
        hidden=(256, 128),
        generic=GenericCamera(focal_px=3000.0, delta_bounds=np.array([[-30, 30], [-30, 30], [-90, 90], [-90, 90]])),
    )


def test_the_pixel_map_moves_points_and_k_alike():
    """Projecting under the mapped K gives the mapped pixels, for a rescale and a crop alike."""
    rng = np.random.default_rng(0)
    X = rng.uniform([-300, -200, 400], [300, 200, 900], (50, 3))
    x = project(X, K_TEST, np.zeros(3), np.zeros(3))
    for pixels in (PixelMap(scale=2.0), PixelMap(scale=0.37, offset=(-120.0, 35.5))):
        K_model = k_matrix(pixels.k_to_model(k_params(K_TEST)))
        np.testing.assert_allclose(pixels.points_to_model(x), project(X, K_model, np.zeros(3), np.zeros(3)), atol=1e-9)
        np.testing.assert_allclose(pixels.K_to_user(K_model), K_TEST, atol=1e-9)
        cov = np.diag([4.0, 4.0, 9.0, 9.0])
        np.testing.assert_allclose(pixels.covariance_to_user(cov), cov / pixels.scale**2)


def test_half_resolution_maps_onto_the_same_model_pixels():
    """The OpenCV half-resolution camera and its points map exactly onto the full one's."""
    x = np.array([[0.0, 0.0], [4031.0, 3023.0], [1234.5, 777.25]])
    full = generic_pixel_map(Camera(K_TEST, SIZE), 3000.0)
    halved = generic_pixel_map(Camera(half(K_TEST), (2016, 1512)), 3000.0)
    assert halved.scale == pytest.approx(2 * full.scale)
    np.testing.assert_allclose(halved.points_to_model((x + 0.5) / 2 - 0.5), full.points_to_model(x), atol=1e-9)
    np.testing.assert_allclose(halved.k_to_model(k_params(half(K_TEST))), full.k_to_model(k_params(K_TEST)))


def test_a_device_model_accepts_its_camera_a_rescale_or_a_crop_and_nothing_else():
    k = k_params(K_TEST)
    assert device_pixel_map(k, SIZE, Camera(K_TEST.copy(), SIZE), "m") is None
    pixels = device_pixel_map(k, SIZE, Camera(half(K_TEST), (2016, 1512)), "m")
    assert pixels.scale == pytest.approx(2.0) and np.allclose(pixels.offset, 0.0, atol=1e-9)
    # A centred 16:9 crop of the sensor (4032 x 2268): the principal point moves up by 378 px.
    crop = K_TEST.copy()
    crop[1, 2] -= 378
    pixels = device_pixel_map(k, SIZE, Camera(crop, (4032, 2268)), "m")
    assert pixels.scale == pytest.approx(1.0) and pixels.offset == pytest.approx((0.0, 378.0))
    # Another lens: a wider fx would need more image than the model's camera has.
    other = K_TEST.copy()
    other[:2, :2] *= 0.9
    with pytest.raises(CameraError, match="no rescale or crop of the model's"):
        device_pixel_map(k, SIZE, Camera(other, SIZE), "model.onnx")
    squashed = K_TEST.copy()
    squashed[1, 1] *= 1.02
    with pytest.raises(CameraError, match="fy / fx"):
        device_pixel_map(k, SIZE, Camera(squashed, SIZE), "model.onnx")


def test_a_generic_spec_round_trips_and_resolves_for_any_camera():
    spec = generic_spec()
    again = ModelSpec.from_json(spec.to_json())
    assert again.to_dict() == spec.to_dict() and again.generic.focal_px == 3000.0
    assert "K_c" not in spec.to_dict() and spec.to_dict()["features"]["depth_mm"] == 500.0
    with pytest.raises(CameraError, match="generic model: it needs your camera"):
        spec.for_camera(None, "generic.onnx")
    for K, size in ((K_TEST, SIZE), (half(K_TEST), (2016, 1512))):
        served = spec.for_camera(Camera(K, size), "generic.onnx")
        k = k_params(served.model.K_c)
        assert k[0] == pytest.approx(3000.0)
        np.testing.assert_allclose(served.model.K_bounds, k[:, None] + spec.generic.delta_bounds)
        np.testing.assert_allclose(served.pixels.K_to_user(served.model.K_c), K, atol=1e-9)
        np.testing.assert_array_equal(served.K_c, K)
        np.testing.assert_allclose(served.pixels.k_to_model(served.K_bounds.T), served.model.K_bounds.T, atol=1e-9)
    with pytest.raises(CameraError, match="more cells than"):
        spec.for_camera(Camera(k_matrix([5.0, 5.0, 2.0, 2.0]), (4, 3)), "generic.onnx")


def test_generic_specs_are_checked_like_any_other():
    d = generic_spec().to_dict()
    for edit, message in (
        (lambda d: d.update(K_c=[1, 1, 1, 1]), "no K_c of its own"),
        (lambda d: d["generic"].update(focal_px="3000"), "generic.focal_px"),
        (lambda d: d["generic"].update(delta_bounds=[[1, 2]] * 4), "low <= 0 <= high"),
        (lambda d: d["features"].pop("depth_mm"), "need depth_mm"),
        (lambda d: d["features"].update(depth_mm=-1), "depth_mm must be a positive number"),
    ):
        bad = ModelSpec.from_json(generic_spec().to_json()).to_dict()
        edit(bad)
        with pytest.raises(ModelError, match=message):
            ModelSpec.from_dict(bad, source="m.onnx")
    assert ModelSpec.from_dict(d).generic is not None


@pytest.mark.parametrize(
    "K, size, message",
    [
        (np.eye(2), SIZE, "shape"),
        (replace(Camera(K_TEST, SIZE)).K * np.nan, SIZE, "finite"),
        (K_TEST, (4032,), "image_size"),
        (K_TEST, (0, 3024), "image_size"),
    ],
)
def test_checked_camera_refuses_bad_values(K, size, message):
    with pytest.raises(CameraError, match=message):
        checked_camera(K, size, "Rectifier.load")


@pytest.mark.parametrize("f", [5e-324, 1e-300, 0.001, 4.25, 1e300])
def test_a_camera_given_in_memory_keeps_the_focal_bound_of_camera_files(f):
    """Issue 33: the bound lived in the file readers only; ``Rectifier.load(K_c=...)`` took any f."""
    K = np.array([[f, 0.0, 2015.5], [0.0, f, 1511.5], [0.0, 0.0, 1.0]])
    with pytest.raises(CameraError, match="times the image's larger side"):
        checked_camera(K, (4032, 3024), "K_c")
    with pytest.raises(CameraError, match="times the image's larger side"):
        Rectifier.load(K_c=K, image_size=(4032, 3024))
