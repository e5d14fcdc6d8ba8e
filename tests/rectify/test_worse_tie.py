"""The worse rule's tie-break (rectify.checks.worse): e(K) > e(K_c) is worse, and so is a NaN; a tie,
e(K) == e(K_c), keeps the candidate. A network that answers Delta K = 0 makes the tie: K is K_c, PnP under
it gives the C0 pose, so its solution is K_c's own and e is e_c to the bit, one by one and in batches,
with and without a lens (whose errors are measured in the distorted image) and refine. Such a frame
keeps its candidate: no "fits worse than K_c", K exactly K_c, Delta K 0, e == e_c (issue 48, failure 6)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from helpers import example_camera
from test_rectifier_camera import rig_frames

from dimenet.runtime.geometry import distort_points
from dimenet.runtime.rectify.checks import loses_to_k_c, worse
from dimenet.runtime.rectify.model import MODEL_NAMES, load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera

DIST = np.array([-0.12, 0.05, 0.0004, -0.0003, -0.01])


def test_the_worse_rule_is_strict_and_a_nan_is_worse():
    e_c = 1.2345
    assert not worse(e_c, e_c) and not loses_to_k_c(e_c, e_c, 3000.0)
    assert worse(np.nextafter(e_c, 2.0), e_c) and not worse(np.nextafter(e_c, 0.0), e_c)
    assert worse(float("nan"), e_c) and worse(e_c, float("nan"))
    e = np.array([e_c, np.nextafter(e_c, 2.0), np.nan, 0.5])
    np.testing.assert_array_equal(worse(e, np.full(4, e_c)), [False, True, True, False])


def zero_network(spec):
    """A stand-in network answering Delta K = 0 for every frame."""
    return SimpleNamespace(
        spec=spec,
        delta_k=lambda f: np.zeros((len(f), 4), np.float32),
        frame_delta_k=lambda f: np.zeros(4),
        source="zero.onnx",
    )


@pytest.mark.parametrize("refine", [False, True])
@pytest.mark.parametrize("lens", [False, True])
@pytest.mark.parametrize("model", MODEL_NAMES)
def test_a_zero_delta_k_ties_and_keeps_its_candidate(frames, model, lens, refine):
    camera = example_camera()
    camera = Camera(camera.K, camera.image_size, DIST if lens else None)
    rect = Rectifier(zero_network(load_model(model).spec), "dimenet", camera)
    p2, p3, valid = rig_frames(frames)
    if lens:
        p2 = np.where(valid[..., None], distort_points(p2, camera.K, DIST), np.nan)
    batch = rect.rectify_batch(p2, p3, valid, refine=refine)
    kept = 0
    for b in range(len(p2)):
        one = rect.rectify(p2[b][valid[b]], p3[b][valid[b]], refine=refine)
        for e, e_c, K, delta_k, fallback in (
            (one.reprojection_error_px, one.reprojection_error_kc_px, one.K, one.delta_k, one.fallback),
            (
                batch.reprojection_error_px[b],
                batch.reprojection_error_kc_px[b],
                batch.K[b],
                batch.delta_k[b],
                batch.fallback[b],
            ),
        ):
            assert fallback is None or "fits worse than K_c" not in fallback, f"frame {b}: a tie fell back: {fallback}"
            assert e == e_c
            np.testing.assert_array_equal(K, rect.K_c)
            np.testing.assert_array_equal(delta_k, np.zeros(4))
            kept += fallback is None
    assert kept >= len(p2)  # most frames keep the candidate (the structure rule may keep K_c on a few)
