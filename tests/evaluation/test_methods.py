"""`evaluate`: the reduction ratio rho, and coverage against K_true when the dataset has it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dimenet.runtime.evaluation.methods import evaluate
from dimenet.runtime.evaluation.metrics import reduction_ratio
from dimenet.runtime.evaluation.predictor import load_onnx_predictor
from dimenet.runtime.evaluation.uncertainty_fit import coverage
from dimenet.runtime.geometry import k_params


def test_coverage_against_k_true_when_the_dataset_has_it(map_model):
    frames, path = map_model
    test = frames.select(frames.frames_in("test"))
    predictor = load_onnx_predictor(path)
    ev = evaluate(test, predictor.spec.K_c, predictor, methods=("dimenet",))
    pred = predictor.predict(test)
    ok = pred.predicted
    expected = coverage(k_params(pred.K[ok]), k_params(test.K_true[ok]), pred.K_cov[ok])
    assert ev.coverage_true == {"dimenet": expected}
    assert ev.coverage_true["dimenet"] != ev.coverage["dimenet"]  # K* is not K_true
    blind = evaluate(replace(test, K_true=None), predictor.spec.K_c, predictor, methods=("dimenet",))
    assert blind.coverage == ev.coverage and blind.coverage_true == {} and "coverage_true" not in blind.to_json()


def test_rho_hand_computed_and_k_c_as_the_prediction_gives_zero(s8_dataset, s8_calibration):
    assert reduction_ratio(3.44, 0.68, 0.45) == pytest.approx((3.44 - 0.68) / (3.44 - 0.45))
    assert reduction_ratio(1.0, 0.5, 1.0) is None  # no gap between K_c and the oracle: undefined
    test = s8_dataset.select(s8_dataset.frames_in("test") & (s8_dataset.scene == "rig"))
    K_c = s8_calibration.K_c
    ev = evaluate(test, K_c, lambda frames: np.broadcast_to(K_c, (frames.n_frames, 3, 3)))
    assert ev.overall.rho == pytest.approx(0.0, abs=1e-12)
    oracle = evaluate(test, K_c, lambda frames: frames.K_true)
    assert oracle.overall.rho > 0.9  # the true K nearly closes the gap to per-frame calibration
