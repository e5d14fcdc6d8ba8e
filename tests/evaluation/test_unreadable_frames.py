"""A frame whose feature cannot be formed (no C0 pose; a data step with no solution) is left unpredicted by
``Predictor.predict`` (``readable_network_k``): K_c, ``predicted`` False, no statistics, the other frames' K as
without it. One such frame failed a whole dataset's prediction before, and with it a training's uncertainty fit
(it draws single planes and sparse points: `dimenet train ... --data-step` stopped on a 9-camera family)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dimenet.runtime.errors import InputError
from dimenet.runtime.evaluation.predictor import load_predictor
from dimenet.runtime.rectify.features import grid_features
from dimenet.runtime.rectify.user_camera import Camera

BROKEN = 2


def degenerate(frames, how: str):
    """The frames with frame BROKEN's inference points put in one 3D point (SQPnP finds no pose) or on one 3D line
    (SQPnP finds one, the data step's Hessian is singular)."""
    points_3d = frames.points_3d.copy()
    idx = np.flatnonzero(frames.infer_mask[BROKEN])
    start = points_3d[BROKEN, idx[0]].copy()
    steps = np.zeros(3) if how == "point" else np.array([1.0, 0.5, 0.0])
    points_3d[BROKEN, idx] = start + np.outer(np.arange(len(idx)), steps)
    return replace(frames, points_3d=points_3d)


@pytest.mark.parametrize(("how", "why"), [("point", "PnP failed"), ("line", "fix no pose")])
def test_a_frame_without_a_feature_is_left_unpredicted_and_the_rest_are_not(s8_dataset, s8_calibration, how, why):
    test = s8_dataset.select(np.flatnonzero(s8_dataset.frames_in("test") & (s8_dataset.scene == "rig"))[:6])
    predictor = load_predictor("default").for_camera(Camera(s8_calibration.K_c, tuple(test.image_size.tolist())))
    broken = degenerate(test, how)
    spec, pixels = predictor.served.model, predictor.served.pixels
    p2 = pixels.points_to_model(broken.points_2d)
    one = (p2[BROKEN : BROKEN + 1], broken.points_3d[BROKEN : BROKEN + 1], broken.infer_mask[BROKEN : BROKEN + 1])
    with pytest.raises(InputError, match=why):
        grid_features(*one, spec.K_c, spec.image_size, spec.features)
    clean, pred = predictor.predict(test), predictor.predict(broken)
    keep = np.arange(test.n_frames) != BROKEN
    assert clean.predicted.all() and pred.predicted.tolist() == keep.tolist()
    np.testing.assert_array_equal(pred.K[BROKEN], s8_calibration.K_c)
    np.testing.assert_allclose(pred.K[keep], clean.K[keep], rtol=0, atol=1e-9)
    assert np.isnan(pred.stats[BROKEN]).all() and np.isfinite(pred.stats[keep]).all()
