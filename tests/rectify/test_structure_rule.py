"""The structure rule (``rectify.checks.structured``): a frame whose residuals under K_c hold smooth
structure that neither OIS nor corner noise makes keeps K_c, with the model's population covariance as
its K_cov, in both modes, one by one and in batches; the reason names the lens when the structure is
radial and the camera has none. The test runs where K removes less than half of e(K_c)
(``checks.STRUCTURE_GATE``): on frames of a camera at rest. Clean simulated frames, with or without
OIS, never trip it."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import model_spec
from test_rectifier_camera import rig_frames

from dimenet.runtime.geometry import distort_points, project, solve_pnp_start
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera

LENS = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])


def _rectifier(frames, mode, dist=None) -> Rectifier:
    """The paper's grid model: the default (any-scene) absorbs part of a left-out lens into f, removing
    more than half of e(K_c), so the rule (consulted below STRUCTURE_GATE) does not run on those frames."""
    size = tuple(int(v) for v in frames.image_size)
    return Rectifier(load_model("paper-rig"), mode, Camera(model_spec(frames).K_c, size, dist))


def _sagged(p2, image_size, amplitude_px):
    """A smooth, non-projective displacement of the points (px): a sheet that is not flat, seen."""
    w, h = image_size
    u, v = (p2[..., 0] - w / 2) / (w / 2), (p2[..., 1] - h / 2) / (w / 2)
    return p2 + amplitude_px * np.stack([u * u * v, (u * u - v * v) * u], -1)


def _without_ois(frames, rng):
    """The rig frames re-imaged under K_c itself (a camera without OIS, or OIS at rest), with 0.4 px
    of corner noise: what is left under K_c is noise and whatever the test adds."""
    p2, p3, valid = rig_frames(frames)
    K_c = model_spec(frames).K_c
    still = np.full_like(p2, np.nan)
    for b in range(len(p2)):
        x, X = p2[b][valid[b]], p3[b][valid[b]]
        still[b][valid[b]] = project(X, K_c, *solve_pnp_start(x, X, K_c)) + rng.normal(0, 0.4, x.shape)
    return still, p3, valid


def _kept(rect, res, words):
    assert res.fallback is not None and all(w in res.fallback for w in words), res.fallback
    assert res.fallback_code == "structure"
    np.testing.assert_array_equal(res.K, rect.K_c)
    np.testing.assert_array_equal(res.K_cov, rect.population_K_cov)
    assert res.reprojection_error_px == res.reprojection_error_kc_px


@pytest.mark.parametrize("ois", [True, False])
@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_clean_simulated_frames_never_trip_the_structure_rule(frames, mode, ois):
    p2, p3, valid = rig_frames(frames) if ois else _without_ois(frames, np.random.default_rng(2))
    batch = _rectifier(frames, mode).rectify_batch(p2, p3, valid)
    assert not any(f is not None and "structure" in f for f in batch.fallback)


@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_a_bent_sheet_keeps_k_c_with_the_population_covariance(frames, mode):
    rect = _rectifier(frames, mode)
    p2, p3, valid = _without_ois(frames, np.random.default_rng(0))
    bent = np.where(valid[..., None], _sagged(p2, frames.image_size, 30.0), np.nan)
    batch = rect.rectify_batch(bent, p3, valid)
    for b in range(len(bent)):
        one = rect.rectify(bent[b][valid[b]], p3[b][valid[b]])
        _kept(rect, one, ["smooth structure", "K_c kept"])
        assert batch.fallback[b] == one.fallback
        np.testing.assert_array_equal(batch.K_cov[b], rect.population_K_cov)
    sigma_c = np.sqrt(rect.population_K_cov[2, 2])
    assert sigma_c > 10  # wide: the OIS range, not the network's confident few px


def test_a_lens_left_out_of_k_c_is_named_and_a_camera_with_it_passes(frames):
    p2, p3, valid = _without_ois(frames, np.random.default_rng(1))
    K_c = model_spec(frames).K_c
    distorted = np.where(valid[..., None], distort_points(p2, K_c, LENS), np.nan)
    res = _rectifier(frames, "dimenet").rectify(distorted[0][valid[0]], p3[0][valid[0]])
    _kept(_rectifier(frames, "dimenet"), res, ["radial lens", "--distortion", "dist_coeffs"])
    with_lens = _rectifier(frames, "dimenet", LENS).rectify_batch(distorted, p3, valid)
    assert not any(f is not None and "structure" in f for f in with_lens.fallback)
