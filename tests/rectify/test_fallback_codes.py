"""Fallback codes (results.FALLBACK_CODES): each refusal and note reaches the result with its code,
in one frame and in a batch, and the code alone tells a refusal (K_c kept) from a note (map gave way)."""

from __future__ import annotations

import copy
import pickle
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import constant_uncertainty, model_spec

from dimenet.runtime.geometry import frame_error_and_depth, solve_pnp_start
from dimenet.runtime.rectify import stages
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.results import FALLBACK_CODES, NOTE, REFUSAL, Fallback


def _stub(spec, delta_k, mode="dimenet"):
    """A Rectifier whose model answers a constant Delta K (px) for every frame."""
    batch = lambda f: np.tile(np.asarray(delta_k, np.float32), (len(f), 1))  # noqa: E731
    net = SimpleNamespace(
        spec=spec, delta_k=batch, frame_delta_k=lambda f: batch(f)[0].astype(np.float64), source="stub model"
    )
    return Rectifier(net, mode)


def _rig(frames, n=2):
    rig = np.flatnonzero(frames.scene == "rig")[:n]
    return frames.points_2d[rig], frames.points_3d[rig], frames.valid[rig]


def test_the_mismatch_rule_has_its_own_code(frames):
    """Points pushed off K_c's projection to 0.0045 fx_c (above the mismatch rule's 0.003 fx_c,
    within the range rule's 0.006 fx_c), a network that hardly moves K: K leaves most of the error."""
    spec = replace(model_spec(frames), K_bounds=np.array([[0.0, 1e4]] * 4))
    p2, p3, valid = _rig(frames, 1)
    x, X = p2[0][valid[0]], p3[0][valid[0]]
    rvec, tvec = solve_pnp_start(x, X, spec.K_c)
    e_c = frame_error_and_depth(x, X, spec.K_c, rvec, tvec)[0]
    fx_c = spec.K_c[0, 0]
    push = 0.0045 * fx_c - e_c
    off = x + push * np.stack([np.cos(np.arange(len(x)) * 2.4), np.sin(np.arange(len(x)) * 2.4)], -1)
    res = _stub(spec, [0.5, 0.0, 0.0, 0.0]).rectify(off, X)
    assert res.fallback_code == "mismatch" and res.fallback.refusal, res.fallback


@pytest.mark.parametrize("code", [c for c, kind in FALLBACK_CODES.items() if kind == NOTE])
def test_a_map_note_reaches_the_result_with_its_code_in_one_frame_and_a_batch(frames, monkeypatch, code):
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(8.0))
    monkeypatch.setattr(stages, "map_rectify", lambda *a, **k: (None, Fallback(code, "gave way")))
    rect = _stub(spec, [0.0, 0.0, 0.0, 0.0], mode="map")
    p2, p3, valid = _rig(frames)
    one = rect.rectify(p2[0][valid[0]], p3[0][valid[0]])
    assert one.fallback_code == code and not one.fallback.refusal
    assert one.fallback == "map: gave way; DIME-Net's K is returned"
    batch = rect.rectify_batch(p2, p3, valid)
    assert batch.fallback_code == (code, code) and batch.fallback == (one.fallback,) * 2


def test_codes_are_few_and_each_is_a_refusal_or_a_note():
    assert set(FALLBACK_CODES.values()) == {REFUSAL, NOTE}
    assert all(c.isidentifier() and c.islower() for c in FALLBACK_CODES)
    with pytest.raises(ValueError, match="unknown fallback code 'worse'"):
        Fallback("worse", "a message")


def test_a_fallback_keeps_its_code_through_pickle_and_copy():
    f = Fallback("no_pose", "no pose under the predicted K")
    for g in (pickle.loads(pickle.dumps(f)), copy.deepcopy(f)):
        assert g == f and g.code == "no_pose" and type(g) is Fallback
