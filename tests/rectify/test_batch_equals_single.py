"""``rectify_batch`` equals ``rectify`` frame by frame over every path the stages take: mode
(dimenet, map) x lens (none, distorted points) x model (a device model on its own camera; the
bundled generic model, whose pixel map to its canonical camera is then used; a device model on
a half-resolution rescale of its camera) x refine x a batch holding a frame that falls back."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import constant_uncertainty, model_spec
from test_rectifier_camera import linear_model, rig_frames, to_half

from dimenet.runtime.geometry import distort_points
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera

DIST = np.array([-0.12, 0.05, 0.0004, -0.0003, -0.01])
NOISY_FRAME = 2  # gets 60 px of noise: beyond the model's range, so it falls back to K_c


@pytest.fixture(scope="module")
def cases(frames):
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(3.0))
    p2, p3, valid = rig_frames(frames)
    p2, p3, valid = p2[:5].copy(), p3[:5], valid[:5]
    noise = np.random.default_rng(0).normal(0.0, 60.0, p2[NOISY_FRAME].shape)
    inside = np.clip(p2[NOISY_FRAME] + noise, 0.0, np.array(spec.image_size) - 1.0)
    p2[NOISY_FRAME] = np.where(valid[NOISY_FRAME, :, None], inside, np.nan)
    own = Camera(spec.K_c, tuple(spec.image_size))
    half_K = spec.K_c.copy()
    half_K[:2, :2] /= 2
    half_K[:2, 2] = to_half(spec.K_c[:2, 2])
    half = Camera(half_K, tuple(int(s) // 2 for s in spec.image_size))
    return (
        {
            "device": (linear_model(spec), own, p2),
            "generic": (load_model(), own, p2),
            "device-half": (linear_model(spec), half, to_half(p2)),
        },
        p3,
        valid,
    )


@pytest.mark.parametrize("evidence", [True, False])
@pytest.mark.parametrize("refine", [False, True])
@pytest.mark.parametrize("lens", [False, True])
@pytest.mark.parametrize("model", ["device", "generic", "device-half"])
@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_batch_equals_single_frames(cases, mode, model, lens, refine, evidence, request):
    """With the evidence rule and without it (the stand-in device network's random Delta K: the rule keeps K_c
    on its frames, so the paths of a standing K run only without it)."""
    if not evidence:
        request.getfixturevalue("without_evidence_rule")
    by_model, p3, valid = cases
    network, camera, p2 = by_model[model]
    if lens:
        camera = Camera(camera.K, camera.image_size, DIST)
        p2 = np.where(valid[..., None], distort_points(p2, camera.K, DIST), np.nan)
    rect = Rectifier(network, mode, camera)
    batch = rect.rectify_batch(p2, p3, valid, refine=refine)
    single = [rect.rectify(p2[b][valid[b]], p3[b][valid[b]], refine=refine) for b in range(len(p2))]
    assert batch.fallback == tuple(s.fallback for s in single)
    assert single[NOISY_FRAME].fallback is not None and "beyond" in single[NOISY_FRAME].fallback
    if not evidence or model == "generic":  # the other frames keep their rectified K
        assert sum(s.fallback is None for s in single) >= 3
    np.testing.assert_allclose(batch.K, [s.K for s in single], rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(batch.delta_k, [s.delta_k for s in single], rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(batch.rvec, [s.rvec for s in single], atol=1e-6)
    np.testing.assert_allclose(batch.tvec, [s.tvec for s in single], rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(batch.reprojection_error_px, [s.reprojection_error_px for s in single], rtol=1e-6)
    np.testing.assert_allclose(batch.reprojection_error_kc_px, [s.reprojection_error_kc_px for s in single], rtol=1e-6)
    for b, s in enumerate(single):
        if s.K_cov is None:
            assert np.isnan(batch.K_cov[b]).all()
        else:
            np.testing.assert_allclose(batch.K_cov[b], s.K_cov, rtol=1e-6, atol=1e-9)
