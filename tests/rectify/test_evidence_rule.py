"""The evidence rule (rectify.checks.unproven, model-v1.md step 10): K stands only where the frame's own points
show its move beyond what fitting K's 4 parameters to their noise gives, the F test's p-value in closed form
(checks.move_p_value) at most EVIDENCE_P; else K_c is kept with code not_significant."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime.rectify import checks
from dimenet.runtime.rectify.checks import EVIDENCE_P, move_p_value, unproven
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera


def test_the_p_value_by_hand():
    # N = 6 points: n = 2, n / 2 = 1, p = q (2 - q); N = 7: n / 2 = 2, p = q^2 (1 + 2 (1 - q)).
    assert move_p_value(0.5, 1.0, 6) == pytest.approx(0.25 * 1.75, rel=1e-15)
    assert move_p_value(np.sqrt(0.5), 1.0, 7) == pytest.approx(0.25 * 2.0, rel=1e-14)
    assert move_p_value(1.0, 1.0, 50) == 1.0 and move_p_value(1.5, 1.0, 50) == 1.0
    assert move_p_value(float("nan"), 1.0, 50) == 1.0 and move_p_value(0.5, float("nan"), 50) == 1.0
    assert move_p_value(0.0, 1.0, 6) == 0.0
    assert move_p_value(1e-200, 1e200, 6) == 0.0 and move_p_value(1.0, float("inf"), 6) == 0.0  # q underflows
    assert move_p_value(0.0, 0.0, 6) == 1.0  # no error to lower: no evidence
    # Scale-free: the same ratio of errors in other units gives the same p.
    assert move_p_value(0.9e-3, 1e-3, 40) == pytest.approx(move_p_value(900.0, 1000.0, 40), rel=1e-12)
    # More points make the same drop of the error more significant.
    assert move_p_value(0.95, 1.0, 20) > move_p_value(0.95, 1.0, 200) > move_p_value(0.95, 1.0, 2000)
    assert unproven(0.99, 1.0, 66) and not unproven(0.5, 1.0, 66)


@pytest.mark.parametrize("n_points", [6, 9, 40])
def test_the_p_value_is_the_tail_of_f_4_n(n_points):
    """Against F(4, n) drawn (numpy's F sampler, 400 000 draws): its tail at the F of each error ratio."""
    n = 2 * n_points - 10
    draws = np.random.default_rng(n_points).f(4, n, 400_000)
    for q in (0.2, 0.5, 0.8, 0.95):
        F = (1.0 - q) / 4.0 / (q / n)
        tail = float(np.mean(draws > F))
        assert move_p_value(np.sqrt(q), 1.0, n_points) == pytest.approx(tail, abs=4e-3), (q, tail)


def _all_frames(frames):
    """Every frame's inference points (rig and natural frames)."""
    return [(frames.points_2d[b][m], frames.points_3d[b][m]) for b, m in enumerate(frames.infer_mask) if m.sum() >= 6]


@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_k_stands_exactly_where_the_frame_shows_the_move(frames, monkeypatch, mode):
    """The bundled model on rig and natural frames: with the rule, a frame whose result without it has p above
    EVIDENCE_P keeps K_c (code not_significant, e = e_c, its C0 pose); every other frame's result is unchanged;
    one frame at a time as in a batch. Both kinds occur."""
    camera = Camera(frames.K_true[0], tuple(int(v) for v in frames.image_size))
    rect = Rectifier.load(K_c=camera.K, image_size=camera.image_size, mode=mode)
    views = _all_frames(frames)
    with monkeypatch.context() as off:
        off.setattr(checks, "EVIDENCE_P", 1.0)
        without = [rect.rectify(x, X) for x, X in views]
    with_rule = [rect.rectify(x, X) for x, X in views]
    shown = kept = 0
    for (x, _), a, b in zip(views, without, with_rule):
        moved = a.fallback is None or not a.fallback.refusal
        p = move_p_value(a.reprojection_error_px, a.reprojection_error_kc_px, len(x))
        if moved and np.any(a.delta_k) and p > EVIDENCE_P:
            kept += 1
            assert b.fallback_code == "not_significant" and b.fallback.refusal
            np.testing.assert_array_equal(b.K, rect.K_c)
            assert b.reprojection_error_px == b.reprojection_error_kc_px == a.reprojection_error_kc_px
            assert f"{len(x)} points" in b.fallback
        else:
            shown += moved
            assert b.fallback == a.fallback
            np.testing.assert_array_equal(b.K, a.K)
            assert b.reprojection_error_px == a.reprojection_error_px
    assert shown and kept, (shown, kept)
    # A batch of the same frames: the same decisions.
    P = max(len(x) for x, _ in views)
    p2, p3 = np.zeros((len(views), P, 2)), np.zeros((len(views), P, 3))
    valid = np.zeros((len(views), P), bool)
    for i, (x, X) in enumerate(views):
        p2[i, : len(x)], p3[i, : len(x)], valid[i, : len(x)] = x, X, True
    batch = rect.rectify_batch(p2, p3, valid)
    assert batch.fallback_code == tuple(r.fallback_code for r in with_rule)
    np.testing.assert_allclose(batch.K, [r.K for r in with_rule], rtol=1e-9, atol=1e-6)
