"""`evaluate`: the reduction ratio rho, coverage against K_true when the dataset has it, the platform's
K (K_platform) as a method and a prior, and datasets with lens distortion."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.methods import evaluate, format_table, fused_prior
from dimenet.runtime.evaluation.metrics import reduction_ratio, reprojection_error_under_k
from dimenet.runtime.evaluation.predictor import load_onnx_predictor
from dimenet.runtime.evaluation.uncertainty_fit import coverage
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.simulator import simulate


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


def test_platform_row_is_the_error_under_k_platform_with_its_stated_sigma(map_model):
    frames, path = map_model
    with_platform = simulate("galaxy-s8", seed=7, natural_frames=2, planar_frames=2, platform_k=True)
    test = with_platform.select(with_platform.frames_in("test"))
    predictor = load_onnx_predictor(path)
    K_c = predictor.spec.K_c
    ev = evaluate(test, K_c, predictor, methods=("platform", "kc", "map", "map+platform"))
    e = reprojection_error_under_k(test.points_2d, test.points_3d, test.valid, test.K_platform)
    row = ev.methods["platform"]["overall"]
    assert row.avg_e == pytest.approx(e.mean()) and row.n_frames == test.n_frames
    assert row.rho > 0.9 and ev.methods["kc"]["overall"].rho == pytest.approx(0.0, abs=1e-12)
    sigma = np.asarray(test.meta["platform_k"]["sigma_px"])
    expected = coverage(
        k_params(test.K_platform), k_params(test.K_true), np.broadcast_to(np.diag(sigma**2), (test.n_frames, 4, 4))
    )
    assert ev.coverage_true["platform"] == expected
    assert ev.fallbacks["platform"] == 0 and "map+platform" in ev.coverage
    table = format_table(ev)
    assert any(line.startswith("platform ") for line in table.splitlines())
    assert any(line.startswith("map+platform ") for line in table.splitlines())


def test_platform_methods_without_k_platform_fail_in_one_line(map_model, tmp_path, capsys):
    frames, path = map_model
    test = frames.select(frames.frames_in("test"))
    with pytest.raises(DatasetError, match="'platform' needs K_platform"):
        evaluate(test, load_onnx_predictor(path).spec.K_c, methods=("kc", "platform"))
    data = write_dataset(frames, tmp_path / "plain.npz")
    assert main(["evaluate", str(data), "--methods", "kc,platform"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'platform' needs K_platform" in err
    unstated = replace(test, K_platform=test.K_true, meta={})
    with pytest.raises(DatasetError, match="stated 1 sigma"):
        evaluate(unstated, test.K_true[0], load_onnx_predictor(path), methods=("map+platform",))


def test_fused_prior_is_the_product_of_the_gaussians():
    k, cov = fused_prior(
        np.array([1.0, 2, 3, 4]), np.diag([1.0, 1, 4, 4]), np.array([3.0, 2, 0, 4]), np.diag([1.0, 3, 2, 4])
    )
    np.testing.assert_allclose(k, [2.0, 2.0, 1.0, 4.0])
    np.testing.assert_allclose(cov, np.diag([0.5, 0.75, 4 / 3, 2.0]))


def test_evaluate_works_on_the_undistorted_points(tmp_path, capsys):
    profile = replace(get_profile("galaxy-s8"), n_train=12, n_test=6)
    ds = simulate(profile, seed=3, dist_coeffs=(0.08, -0.15, 0.0, 0.0))
    results = []
    for name, data in (("distorted", ds), ("undistorted", ds.undistorted())):
        assert (
            main(["evaluate", str(write_dataset(data, tmp_path / f"{name}.npz")), "--methods", "kc,self", "--json"])
            == 0
        )
        results.append(json.loads(capsys.readouterr().out))
    assert results[0] == results[1]


def test_the_runtime_methods_return_the_rectifiers_k():
    """evaluate's rectify and rectify-map give the K `dimenet rectify` gives on the inference points alone, every
    rule applied (the rules read none of the board a natural frame is scored on)."""
    from dimenet.runtime.evaluation.methods import runtime_estimate
    from dimenet.runtime.evaluation.predictor import load_predictor
    from dimenet.runtime.rectify.rectifier import Rectifier
    from dimenet.runtime.rectify.user_camera import Camera
    from dimenet.runtime.sim.simulator import simulate

    frames = simulate("galaxy-s8", seed=3, natural_frames=3)
    test = frames.select(frames.frames_in("test"))
    camera = Camera(frames.K_true[0], tuple(int(v) for v in frames.image_size))
    predictor = load_predictor("default").for_camera(camera)
    for mode in ("dimenet", "map"):
        est = runtime_estimate(test, predictor, mode)
        rect = Rectifier.load(K_c=camera.K, image_size=camera.image_size, mode=mode)
        r = rect.rectify_batch(test.points_2d, test.points_3d, test.infer_mask, infer_mask=test.infer_mask)
        np.testing.assert_array_equal(est.K, r.K)
        natural = test.scene == "natural"
        assert natural.any() and (test.valid[natural].sum(-1) > test.infer_mask[natural].sum(-1)).all()
        assert est.fallbacks == sum(f is not None and not f.startswith("map:") for f in r.fallback)
