"""Each hot-path twin of the rectifier (beside its reference: geometry.projection, rectify.checks,
rectify.spec) against that numpy reference, on ordinary and edge inputs."""

import cv2
import numpy as np
import pytest
from helpers import random_frames

from dimenet.runtime import geometry as g
from dimenet.runtime.geometry import frame_error_and_depth, frame_mean_norm, frame_residuals
from dimenet.runtime.rectify.checks import ImageBounds, all_inside
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.spec import ModelSpec, frame_within_bounds


def _frame(seed=0, points=320):
    x, X, K, rvec, tvec = random_frames(np.random.default_rng(seed), frames=1, points=points, noise_px=0.7)
    return np.ascontiguousarray(x[0]), np.ascontiguousarray(X[0]), K[0].copy(), rvec[0], tvec[0]


def test_frame_residuals_equal_the_reference_residuals():
    x, X, K, rvec, tvec = _frame()
    R = cv2.Rodrigues(rvec)[0]
    reference = g.reprojection_residuals(x, X, K, R, tvec)  # (2, N)
    np.testing.assert_allclose(frame_residuals(x, X, K, R, tvec).T, reference, rtol=0, atol=1e-9)
    assert np.abs(reference).max() > 0.1  # noisy points: the residuals are not trivially zero


def test_frame_mean_norm_and_error_equal_the_reference_means():
    x, X, K, rvec, tvec = _frame(1)
    d = g.reprojection_residuals(x, X, K, cv2.Rodrigues(rvec)[0], tvec)
    assert frame_mean_norm(np.ascontiguousarray(d)) == pytest.approx(g.mean_residual_norms(d[None], None)[0], rel=1e-12)
    reference = g.mean_reprojection_error(x[None], X[None], None, K, rvec[None], tvec[None])[0]
    e, depth = frame_error_and_depth(x, X, K, rvec, tvec)
    assert e == pytest.approx(reference, rel=1e-9)
    assert depth == pytest.approx(g.min_depths(X[None], None, rvec[None], tvec[None])[0], rel=1e-12) and depth > 0


@pytest.mark.parametrize(
    "edit",
    [
        lambda x, X: None,  # all inside
        lambda x, X: x.__setitem__((3, 0), -0.5),  # on the edge: still inside
        lambda x, X: x.__setitem__((3, 0), -0.51),
        lambda x, X: x.__setitem__((5, 1), 3023.6),
        lambda x, X: x.__setitem__((7, 0), np.nan),
        lambda x, X: X.__setitem__((9, 2), np.inf),
        lambda x, X: X.__setitem__((9, 2), np.finfo(np.float64).max),
    ],
)
def test_all_inside_equals_the_reference_mask(edit):
    bounds = ImageBounds((4032, 3024))
    x, X = np.random.default_rng(2).uniform(0, 3000, (40, 2)), np.random.default_rng(3).uniform(-100, 100, (40, 3))
    edit(x, X)
    assert all_inside(bounds, x, X) == bool(bounds.inside(x, X).all())


@pytest.mark.parametrize(
    "k",
    [
        [3000.0, 3000.0, 2016.0, 1512.0],
        [3100.0, 3000.0, 2016.0, 1512.0],
        [3000.0, 2900.0, 2016.0, 1512.0],
        [3000.0, 3000.0, np.nan, 1512.0],
        [3000.0, 3000.0, 2016.0, np.inf],
        [2950.0, 3050.0, 1966.0, 1462.0],
    ],
)
def test_frame_within_bounds_is_the_spec_rule(k):
    bounds = np.array([[2950.0, 3050.0], [2950.0, 3050.0], [1966.0, 2066.0], [1462.0, 1562.0]])
    spec = ModelSpec(
        features=FeatureSpec(),
        K_c=g.k_matrix([3000.0, 3000.0, 2016.0, 1512.0]),
        image_size=(4032, 3024),
        K_bounds=bounds,
        hidden=(8,),
    )
    assert frame_within_bounds(k, bounds.tolist()) == bool(spec.k_within_bounds(np.array(k)))
