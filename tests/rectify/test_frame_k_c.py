"""A frame's own prior (``Rectifier.rectify(..., K_c=...)``, issue 51 step 4): the frame is rectified as a
Rectifier built for that K_c would rectify it (both modes, with a lens too), the Rectifier's own K_c changes
nothing, and a device model or a K_c no camera has is an InputError."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import DEVICE_MODEL, example_camera

from dimenet.runtime.errors import InputError
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import checked_camera

LENS = np.array([0.08, -0.12, 0.0005, -0.0003, 0.02])


def _frames(frames, n=4):
    """n rig frames of the session's set: (points_2d, points_3d) of each frame's valid points."""
    rig = np.flatnonzero(frames.scene == "rig")[:n]
    return [(frames.points_2d[i][frames.valid[i]], frames.points_3d[i][frames.valid[i]]) for i in rig]


def _same(a, b) -> None:
    for name in ("K", "rvec", "tvec", "K_cov"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None) and (x is None or np.array_equal(x, y)), name
    assert a.reprojection_error_px == b.reprojection_error_px
    assert a.reprojection_error_kc_px == b.reprojection_error_kc_px
    assert a.fallback == b.fallback and a.fallback_code == b.fallback_code


def _moved(K: np.ndarray, seed: int) -> np.ndarray:
    """K with its focal lengths scaled by up to 1 % and c moved by up to 25 px (a platform's per-frame K)."""
    rng = np.random.default_rng(seed)
    K = K.copy()
    K[0, 0] *= 1 + rng.uniform(-0.01, 0.01)
    K[1, 1] *= 1 + rng.uniform(-0.01, 0.01)
    K[:2, 2] += rng.uniform(-25, 25, 2)
    return K


@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_a_frame_s_k_c_rectifies_as_a_rectifier_built_for_it(frames, mode):
    camera = example_camera()
    served = Rectifier.load(K_c=camera.K, image_size=camera.image_size, mode=mode)
    for k, (p2, p3) in enumerate(_frames(frames)):
        K_frame = _moved(camera.K, k)
        own = Rectifier.load(K_c=K_frame, image_size=camera.image_size, mode=mode)
        got = served.rectify(p2, p3, K_c=K_frame)
        _same(got, own.rectify(p2, p3))
        assert got.reprojection_error_kc_px != served.rectify(p2, p3).reprojection_error_kc_px  # e_c: its own K_c
        _same(served.rectify(p2, p3, K_c=camera.K), served.rectify(p2, p3))


def test_with_a_lens_the_coefficients_keep_the_k_they_were_stated_about(frames):
    camera = example_camera()
    model = load_model(None)
    lens = Rectifier(model, "dimenet", checked_camera(camera.K, camera.image_size, "camera", LENS))
    for k, (p2, p3) in enumerate(_frames(frames, 2)):
        K_frame = _moved(camera.K, 10 + k)
        own = Rectifier(model, "dimenet", checked_camera(K_frame, camera.image_size, "camera", LENS, camera.K))
        _same(lens.rectify(p2, p3, K_c=K_frame), own.rectify(p2, p3))


def test_a_device_model_and_a_k_c_no_camera_has_are_input_errors(frames):
    (p2, p3), *_ = _frames(frames, 1)
    device = Rectifier.load(DEVICE_MODEL)
    with pytest.raises(InputError, match="device model: it serves its own K_c"):
        device.rectify(p2, p3, K_c=device.K_c)
    camera = example_camera()
    served = Rectifier.load(K_c=camera.K, image_size=camera.image_size)
    bad = camera.K.copy()
    bad[0, 2] = 1e5  # the principal point far outside the image
    for K in (bad, np.eye(3), np.full((3, 3), np.nan), [[1.0, 2.0]]):
        with pytest.raises(InputError, match="the frame's K_c"):
            served.rectify(p2, p3, K_c=K)
