"""Hostile frames: a typed InputError or K_c's solution with a reason, never a confident wrong K,
never a pose with a point behind the camera (issue 20's reproducers)."""

import cv2
import numpy as np
import pytest
from helpers import default_rectifier

from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import min_depths
from dimenet.runtime.rectify.checks import MAX_KC_ERROR_F


@pytest.fixture(scope="module", params=["dimenet", "map"])
def bundled(request):
    return default_rectifier(request.param)


def _rig_frame(frames, b=0):
    rig = np.flatnonzero(frames.scene == "rig")[b]
    m = frames.valid[rig]
    return frames.points_2d[rig][m], frames.points_3d[rig][m], frames.K_true[rig]


def _half_behind(frames):
    """Half of a rig frame's 3D points reflected through the camera centre: every pixel is still
    the pinhole projection of its point, but those points lie behind the camera."""
    x, X, K = _rig_frame(frames)
    _, rvec, tvec = cv2.solvePnP(X, x, K, None, flags=cv2.SOLVEPNP_SQPNP)
    R, t = cv2.Rodrigues(rvec)[0], tvec.ravel()
    Xc = X @ R.T + t
    Xc[::2] *= -1.0
    return x, (Xc - t) @ R


def _shuffled(frames):
    x, X, _ = _rig_frame(frames)
    return x[np.random.default_rng(0).permutation(len(x))], X


def _y_flipped(frames):
    x, X, _ = _rig_frame(frames)
    return np.c_[x[:, 0], 3023.0 - x[:, 1]], X


def _noisy_30px(frames):
    x, X, _ = _rig_frame(frames)
    return np.clip(x + np.random.default_rng(1).normal(0, 30.0, x.shape), 0, [4031, 3023]), X


HOSTILE = {"half behind": _half_behind, "shuffled": _shuffled, "y-flipped": _y_flipped, "30 px noise": _noisy_30px}


def _assert_no_confident_wrong_k(rect, x, X, res):
    """Either K_c's solution with a reason, or a pose with every point in front of the camera."""
    Z = X @ cv2.Rodrigues(res.rvec)[0][2] + res.tvec[2]
    assert Z.min() > 0, "a pose with a point behind the camera was returned"
    assert res.fallback is not None and res.fallback.refusal
    np.testing.assert_array_equal(res.K, rect.K_c)
    _assert_population_cov(rect, res.K_cov)


def _assert_population_cov(rect, K_cov):
    """A frame that keeps K_c has the population covariance (a spec 1.6 model), else none."""
    if rect.population_K_cov is None:
        assert K_cov is None or np.all(np.isnan(K_cov))
    else:
        np.testing.assert_array_equal(K_cov, rect.population_K_cov)


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_frames_fall_back_or_are_refused(bundled, frames, case):
    x, X = HOSTILE[case](frames)
    try:
        res = bundled.rectify(x, X)
    except InputError as exc:
        assert "behind the camera" in str(exc)
        return
    _assert_no_confident_wrong_k(bundled, x, X, res)


@pytest.mark.parametrize("case", ["y-flipped", "30 px noise"])  # shuffled points: refused (behind)
def test_out_of_range_frames_name_the_likely_cause_in_single_and_batch(bundled, frames, case):
    x, X = HOSTILE[case](frames)
    res = bundled.rectify(x, X)
    assert "beyond" in res.fallback and "another camera, resolution or unit" in res.fallback
    assert res.fallback_code == "out_of_range"
    assert res.reprojection_error_kc_px > MAX_KC_ERROR_F * bundled.K_c[0, 0]
    good_x, good_X, _ = _rig_frame(frames, 1)
    n = min(len(x), len(good_x))
    batch = bundled.rectify_batch(np.stack([good_x[:n], x[:n]]), np.stack([good_X[:n], X[:n]]), np.ones((2, n), bool))
    assert batch.fallback[0] is None or not batch.fallback[0].refusal
    assert "beyond" in batch.fallback[1] and batch.fallback_code[1] == "out_of_range"
    np.testing.assert_array_equal(batch.K[1], bundled.K_c)
    _assert_population_cov(bundled, None if batch.K_cov is None else batch.K_cov[1])


def test_points_behind_the_camera_under_k_c_are_refused_in_a_batch_naming_the_frame(bundled, frames):
    x, X = _half_behind(frames)
    good_x, good_X, _ = _rig_frame(frames, 1)
    n = min(len(x), len(good_x))
    p2, p3 = np.stack([good_x[:n], x[:n]]), np.stack([good_X[:n], X[:n]])
    try:
        batch = bundled.rectify_batch(p2, p3, np.ones((2, n), bool))
    except InputError as exc:
        assert str(exc).startswith("frame 1:") and "behind the camera" in str(exc)
        return
    assert np.all(min_depths(p3, None, batch.rvec, batch.tvec) > 0)


@pytest.mark.parametrize("value", [1e78, -1e200, 1e12])
def test_huge_coordinates_are_an_input_error_not_an_overflow(bundled, frames, value):
    x, X, _ = _rig_frame(frames)
    X = X.copy()
    X[3, 1] = value
    with pytest.raises(InputError, match="beyond"):
        bundled.rectify(x, X)
    with pytest.raises(InputError, match="frame 0: points_3d: point 3"):
        bundled.rectify_batch(x[None], X[None], np.ones((1, len(x)), bool))


def test_an_empty_batch_is_an_input_error(bundled):
    with pytest.raises(InputError, match="empty batch"):
        bundled.rectify_batch(np.zeros((0, 10, 2)), np.zeros((0, 10, 3)), np.zeros((0, 10), bool))


def test_ordinary_frames_stay_in_range(bundled, frames):
    """The range rule leaves the simulated test frames (rig, natural) alone."""
    test = np.flatnonzero(frames.split == "test")
    batch = bundled.rectify_batch(frames.points_2d[test], frames.points_3d[test], frames.valid[test])
    assert not any(f is not None and "beyond" in f for f in batch.fallback)


def test_repeated_correspondences_do_not_count_toward_the_minimum(bundled, frames):
    x, X, _ = _rig_frame(frames)
    spread = np.linspace(0, len(x) - 1, 6).astype(int)  # six points over the rig, not one board row
    p2, p3 = np.resize(x[spread[:5]], (40, 2)), np.resize(X[spread[:5]], (40, 3))  # 40 rows, 5 distinct points
    with pytest.raises(InputError, match="5 distinct points of 40: rectification needs at least 6"):
        bundled.rectify(p2, p3)
    with pytest.raises(InputError, match="frame 1: 5 distinct valid points of 40"):
        bundled.rectify_batch(np.stack([x[:40], p2]), np.stack([X[:40], p3]), np.ones((2, 40), bool))
    bundled.rectify(np.resize(x[spread], (40, 2)), np.resize(X[spread], (40, 3)))  # six distinct ones are enough
