"""Beyond the paper: the uncertainty model, MAP rectification, the self baseline, planar scenes
and `dimenet evaluate --methods`."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from helpers import K_TEST, random_frames
from test_export import model_spec, random_model_file

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import InputError, ModelError
from dimenet.runtime.evaluation.conditions import one_plane
from dimenet.runtime.evaluation.methods import evaluate
from dimenet.runtime.evaluation.predictor import load_onnx_predictor
from dimenet.runtime.evaluation.self_calibration import self_calibrate
from dimenet.runtime.evaluation.uncertainty_fit import coverage, fit_data_correlation, fit_uncertainty
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.geometry import (
    covariance_invariants,
    covariance_invariants_batch,
    k_matrix,
    k_params,
    project,
    solve_pnp_start,
)
from dimenet.runtime.geometry.least_squares import calibrate
from dimenet.runtime.rectify.map_fit import map_fit, map_rectify, turned_to_principal_point
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.uncertainty import NOISE_SCALE_PX, T_FLOOR, Uncertainty, input_statistics, thickness
from dimenet.runtime.sim.simulator import simulate

K_NET_OFFSET = np.array([6.0, -5.0, 8.0, -7.0])  # px: the "network's" error in the MAP tests


def constant_uncertainty(sigma_px: float) -> Uncertainty:
    coef = np.zeros((4, 5))
    coef[:, 0] = np.log(sigma_px)
    return Uncertainty(coef=coef, correlation=np.eye(4))


def test_uncertainty_fit_recovers_a_known_noise_model():
    rng = np.random.default_rng(0)
    n = 4000
    stats = np.c_[
        np.log(rng.uniform(60, 320, n)),
        np.log(rng.uniform(8, 48, n)),
        np.log(rng.uniform(0.3, 10, n)),
        np.log(rng.uniform(1e-6, 0.3, n)),
    ]
    true_coef = np.array(
        [
            [1.0, -0.5, 0.0, 0.3, -0.1],
            [0.5, 0.0, -0.2, 0.6, 0.0],
            [2.0, -0.3, -0.1, 0.0, -0.2],
            [1.5, 0.0, 0.0, 0.4, -0.05],
        ]
    )
    corr = np.array([[1, 0.8, 0, 0], [0.8, 1, 0, 0], [0, 0, 1, -0.3], [0, 0, -0.3, 1.0]])
    sigma = np.exp(np.c_[np.ones(n), stats] @ true_coef.T)
    residuals = (rng.multivariate_normal(np.zeros(4), corr, n)) * sigma
    model = fit_uncertainty(residuals, stats)
    np.testing.assert_allclose(model.coef[:, 1:], true_coef[:, 1:], atol=0.05)  # slopes
    np.testing.assert_allclose(model.sigma(stats), sigma, rtol=0.15)
    np.testing.assert_allclose(model.correlation, corr, atol=0.05)
    fresh = rng.multivariate_normal(np.zeros(4), corr, n) * sigma
    for share in coverage(fresh, np.zeros_like(fresh), model.covariance(stats)).values():
        assert 0.65 < share < 0.71
    again = Uncertainty.from_dict(json.loads(json.dumps(model.to_dict())))
    np.testing.assert_array_equal(again.coef, model.coef)
    one = model.frame_covariance(100, 20, 2.5, 0.01)
    np.testing.assert_allclose(one, model.covariance(np.log([[100, 20, 2.5, 0.01]]))[0], rtol=1e-12)


def test_a_spec_1_1_uncertainty_reads_the_first_three_statistics():
    coef = np.array([[1.0, -0.5, 0.0, 0.3]] * 4)
    old = Uncertainty.from_dict(
        {
            "parameters": ["fx", "fy", "cx", "cy"],
            "statistics": ["1", "log_points", "log_cells", "log_pmd"],
            "coef": coef.tolist(),
            "correlation": np.eye(4).tolist(),
        }
    )
    stats = np.log([[100, 20, 2.5, 1e-6], [100, 20, 2.5, 0.3]])  # the thickness does not matter to it
    np.testing.assert_allclose(old.sigma(stats), np.exp(1.0 - 0.5 * np.log(100) + 0.3 * np.log(2.5)) * np.ones((2, 4)))
    np.testing.assert_allclose(old.frame_covariance(100, 20, 2.5, 0.3), old.covariance(stats)[1], rtol=1e-12)


def point_thickness(points_3d: np.ndarray) -> float:
    return thickness(*covariance_invariants(np.ascontiguousarray(points_3d, dtype=np.float64)))


def test_point_thickness_hand_computed_cases():
    axes = np.vstack([np.eye(3), -np.eye(3)])  # covariance I/3: an isotropic cloud
    assert point_thickness(axes) == pytest.approx(1 / 3)
    box = axes * [2.0, 1.0, 0.1]  # covariance diag(4, 1, 0.01) / 3: det tr / e2^2 = 0.04 * 5.01 / 4.05^2
    assert point_thickness(box * 250.0) == pytest.approx(0.04 * 5.01 / 4.05**2)  # scale free
    rng = np.random.default_rng(0)
    plane = np.c_[rng.normal(size=(50, 2)), np.zeros(50)] @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    assert point_thickness(np.ascontiguousarray(plane)) < 1e-12
    assert point_thickness(np.outer(rng.normal(size=20), [1.0, 2.0, 3.0])) == 0.0  # a line
    mask = np.array([[True] * 6, [True] * 3 + [False] * 3])
    stats = input_statistics(
        np.ones((2, 6)), mask.sum(1), np.ones(2), covariance_invariants_batch(np.stack([axes, box]), mask), 2
    )
    assert stats[0, 3] == pytest.approx(np.log(1 / 3)) and stats[1, 3] == np.log(T_FLOOR)  # 3 points: a plane


def test_one_plane_keeps_the_inference_points_of_one_board(s8_dataset):
    frames = s8_dataset.select(np.flatnonzero(s8_dataset.scene == "rig")[:6])
    planes = one_plane(frames, np.random.default_rng(0))
    for f in range(frames.n_frames):
        kept = planes.infer_mask[f]
        assert np.all(frames.infer_mask[f] >= kept) and 4 <= kept.sum() < frames.infer_mask[f].sum()
        assert point_thickness(np.ascontiguousarray(frames.points_3d[f][kept])) < 1e-9
        assert point_thickness(np.ascontiguousarray(frames.points_3d[f][frames.infer_mask[f]])) > 1e-3


def test_uncertainty_refuses_bad_input():
    with pytest.raises(InputError, match="needs >= 20 frames"):
        fit_uncertainty(np.ones((5, 4)), np.ones((5, 4)))
    with pytest.raises(InputError, match=r"statistics must be \(F, 4\)"):
        fit_uncertainty(np.ones((40, 4)), np.ones((40, 3)))
    with pytest.raises(ValueError, match="not positive definite"):
        Uncertainty.from_dict({"coef": np.zeros((4, 4)).tolist(), "correlation": np.ones((4, 4)).tolist()})
    with pytest.raises(ValueError, match="distinct names"):
        Uncertainty.from_dict(
            {
                "statistics": ["1", "log_points", "log_depth"],
                "coef": np.zeros((4, 3)).tolist(),
                "correlation": np.eye(4).tolist(),
            }
        )


def test_posterior_scale_hand_computed():
    u = replace(constant_uncertainty(1.0), data_correlation=np.array([0.0, 0.2, 0.5, 1.0]))
    # s = s0: half the correlation applies (w = 1/2); r = 1/2: sqrt(r (1 - r)) = 1/2.
    np.testing.assert_allclose(u.posterior_scale([0.5] * 4, NOISE_SCALE_PX), np.sqrt([1.0, 1.1, 1.25, 1.5]), rtol=1e-12)
    # A posterior equal to the prior (r = 1) or set by the data alone (r = 0) is not widened,
    # nor is a noise-free frame.
    assert u.posterior_scale([1.0, 0.0, 1.0, 0.0], 5.0) == [1.0] * 4
    assert u.posterior_scale([0.5] * 4, 0.0) == [1.0] * 4


def test_data_correlation_fit_recovers_a_known_correlation():
    rng = np.random.default_rng(0)
    n = 20000
    sigma = rng.uniform(0.5, 5.0, (n, 4))
    ratio = rng.uniform(0.05, 0.95, (n, 4))
    noise = rng.uniform(0.3, 8.0, n)
    rho = np.array([0.0, 0.3, 0.8, 0.0])
    w = noise**2 / (noise**2 + NOISE_SCALE_PX**2)
    widened = sigma * np.sqrt(1 + 2 * rho * w[:, None] * np.sqrt(ratio * (1 - ratio)))
    errors = rng.normal(size=(n, 4)) * widened
    errors[:, 0] *= 0.8  # over-covered already: no correlation to add
    errors[:, 3] *= 3.0  # beyond any correlation: the largest, 1
    np.testing.assert_allclose(fit_data_correlation(errors, sigma, ratio, noise), [0.0, 0.3, 0.8, 1.0], atol=0.05)
    with pytest.raises(InputError, match=r"\(F, 4\)"):
        fit_data_correlation(errors[:, :3], sigma, ratio, noise)
    with pytest.raises(InputError, match="finite"):
        fit_data_correlation(errors, sigma * np.nan, ratio, noise)
    with pytest.raises(ValueError, match=r"data_correlation must be 4 values in \[0, 1\]"):
        replace(constant_uncertainty(1.0), data_correlation=np.array([0.0, 0.0, 1.5, 0.0]))


def test_map_fit_widens_its_posterior_by_the_data_correlation():
    x, X, K = _frame(np.random.default_rng(1), noise_px=3.0)
    k_net = k_params(K) + K_NET_OFFSET
    start = solve_pnp_start(x, X, k_matrix(k_net))
    prior = np.diag([4.0, 4.0, 100.0, 100.0])
    plain = map_fit(x, X, k_net, prior, *start)
    independent = map_fit(x, X, k_net, prior, *start, uncertainty=constant_uncertainty(1.0))
    np.testing.assert_array_equal(independent.k_cov, plain.k_cov)  # rho = 0: nothing to widen
    u = replace(constant_uncertainty(1.0), data_correlation=np.array([0.0, 0.4, 0.6, 1.0]))
    widened = map_fit(x, X, k_net, prior, *start, uncertainty=u)
    np.testing.assert_array_equal(widened.k, plain.k)  # the estimate itself does not change
    assert 2.0 < plain.noise_px < 4.0  # the frame's 3 px noise, estimated
    scale = np.sqrt(
        1
        + 2
        * u.data_correlation
        * plain.noise_px**2
        / (plain.noise_px**2 + NOISE_SCALE_PX**2)
        * np.sqrt((r := np.diag(plain.k_cov) / np.diag(prior)) * (1 - r))
    )
    np.testing.assert_allclose(widened.k_cov, plain.k_cov * np.outer(scale, scale), rtol=1e-12)
    assert scale[0] == 1.0 and np.all(scale[1:] > 1.0)


def _frame(rng, planar=False, noise_px=0.5, points=120):
    x, X, K, rvec, tvec = random_frames(rng, 1, points, noise_px=noise_px, planar=planar)
    return x[0], X[0], K[0]


def test_map_with_a_vague_prior_is_self_calibration():
    x, X, K = _frame(np.random.default_rng(1))
    k_net = k_params(K) + K_NET_OFFSET
    start = solve_pnp_start(x, X, k_matrix(k_net))
    fit = map_fit(x, X, k_net, np.eye(4) * 1e10, *start, iterations=10)
    self_k = k_params(calibrate(x[None], X[None], np.ones((1, len(x)))).K[0])
    np.testing.assert_allclose(fit.k, self_k, atol=1e-3)
    # One step (the runtime's default) already removes > 97 % of the start's 6-8 px error.
    np.testing.assert_allclose(map_fit(x, X, k_net, np.eye(4) * 1e10, *start).k, self_k, atol=0.2)


def test_one_step_from_the_c0_pose_turned_to_k_net_lands_at_the_optimum():
    x, X, K = _frame(np.random.default_rng(1))
    k_net = k_params(K) + K_NET_OFFSET
    self_k = k_params(calibrate(x[None], X[None], np.ones((1, len(x)))).K[0])
    K_c = k_matrix(k_net - [10.0, 10.0, 40.0, 30.0])  # the runtime's start: the pose under K_c, f and c off k_net
    rvec, tvec = solve_pnp_start(x, X, K_c)
    R, t = turned_to_principal_point(cv2.Rodrigues(rvec)[0], tvec, K_c, k_net)
    # Turned, the pose images the points under k_net about where they were under K_c (first order).
    under_k_c = project(X, K_c, rvec, tvec)
    turned = np.abs(project(X, k_matrix(k_net), cv2.Rodrigues(R)[0].ravel(), t) - under_k_c).max()
    assert turned < 0.25 * np.abs(project(X, k_matrix(k_net), rvec, tvec) - under_k_c).max()
    one_step = map_fit(x, X, k_net, np.eye(4) * 1e10, rvec, tvec, K_start=K_c).k
    unturned = map_fit(x, X, k_net, np.eye(4) * 1e10, rvec, tvec).k
    assert np.abs(one_step - self_k).max() < 0.2 < np.abs(unturned - self_k).max()


def test_map_with_a_sharp_prior_keeps_the_network_k_and_the_pnp_pose():
    x, X, K = _frame(np.random.default_rng(2))
    k_net = k_params(K) + K_NET_OFFSET
    start = solve_pnp_start(x, X, k_matrix(k_net))
    fit = map_fit(x, X, k_net, np.eye(4) * 1e-10, *start, iterations=5)
    np.testing.assert_allclose(fit.k, k_net, atol=1e-6)
    assert np.all(np.linalg.eigvalsh(fit.k_cov) > 0) and np.all(np.diag(fit.k_cov) <= 1e-10 * (1 + 1e-6))


def test_map_rectify_refuses_a_fit_whose_step_raised_the_cost():
    x, X, K, rvec, tvec = random_frames(np.random.default_rng(0), 1, 60, noise_px=0.5)
    x, X, k, bounds = x[0], X[0], k_params(K[0]), np.stack([k_params(K[0]) - 500, k_params(K[0]) + 500], -1)
    near = map_rectify(x, X, k, np.eye(4) * 25.0, bounds, K[0], pose=(rvec[0], tvec[0]))
    assert near[1] is None and near[0].steps == 1
    # From a start 1 rad off, the one Gauss-Newton step overshoots: the start is no answer.
    far = map_rectify(x, X, k, np.eye(4) * 25.0, bounds, K[0], pose=(rvec[0] + [1.0, 0.0, 0.0], tvec[0]))
    assert far == (None, "the MAP step did not lower the cost")


def test_map_on_one_planar_view_follows_the_prior_where_the_data_says_nothing():
    x, X, K = _frame(np.random.default_rng(3), planar=True)
    with pytest.raises(Exception, match="coplanar"):
        calibrate(x[None], X[None], np.ones((1, len(x))))
    k_net = k_params(K) + K_NET_OFFSET
    prior = np.diag([25.0, 25.0, 25.0, 25.0])
    fit = map_fit(x, X, k_net, prior, *solve_pnp_start(x, X, k_matrix(k_net)), iterations=10)
    assert np.all(np.isfinite(fit.k)) and np.all(np.abs(fit.k - k_params(K)) < 4 * 5.0)
    # The posterior is never wider than the prior (the data only add information).
    assert np.all(np.linalg.eigvalsh(prior - fit.k_cov) >= -1e-9)


def test_self_calibration_falls_back_on_planar_and_too_few_points():
    frames = simulate("galaxy-s8", seed=3, planar_frames=3)
    test = frames.select(frames.frames_in("test"))
    K_c = k_matrix(k_params(K_TEST))
    infer = test.infer_mask.copy()
    infer[0] = False
    infer[0, np.flatnonzero(test.valid[0])[:5]] = True
    result = self_calibrate(replace(test, infer_mask=infer), K_c)
    assert "5 inference points" in result.fallback[0] and np.all(result.K[0] == K_c)
    planar = np.flatnonzero(test.scene == "planar")
    assert all("ill-posed" in result.fallback[f] and "coplanar" in result.fallback[f] for f in planar)
    assert np.all(result.K[planar] == K_c)
    rig = np.flatnonzero(test.scene == "rig")[1:]
    assert all(result.fallback[f] is None for f in rig)
    assert np.abs(k_params(result.K[rig]) - k_params(test.K_true[rig])).mean() < 2.0


def test_planar_frames_infer_from_one_board_and_leave_the_other_frames_alone():
    plain = simulate("galaxy-s8", seed=5, natural_frames=2)
    ds = simulate("galaxy-s8", seed=5, natural_frames=2, planar_frames=4)
    np.testing.assert_array_equal(ds.points_2d[: plain.n_frames], plain.points_2d)
    planar = ds.scene == "planar"
    assert planar.sum() == 4 and np.all(ds.split[planar] == "test") and ds.meta["planar_frames"] == 4
    for f in np.flatnonzero(planar):
        X = ds.points_3d[f][ds.infer_mask[f]]
        assert np.linalg.svd(X - X.mean(0), compute_uv=False)[2] < 1e-6  # one board: coplanar
        assert ds.valid[f].sum() > ds.infer_mask[f].sum() >= 6


@pytest.fixture(scope="module")
def map_model(tmp_path_factory):
    frames = simulate("galaxy-s8", seed=7, natural_frames=2, planar_frames=2)
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(8.0))
    return frames, random_model_file(tmp_path_factory.mktemp("map") / "map.onnx", spec)


def test_rectifier_map_mode_fits_at_least_as_well_and_reports_its_posterior(map_model):
    frames, path = map_model
    dimenet, fused = Rectifier.load(path), Rectifier.load(path, mode="map")
    rig = np.flatnonzero(frames.scene == "rig")[-4:]
    for b in rig:
        m = frames.valid[b]
        a, c = (
            dimenet.rectify(frames.points_2d[b][m], frames.points_3d[b][m]),
            fused.rectify(frames.points_2d[b][m], frames.points_3d[b][m]),
        )
        if a.fallback is None:
            np.testing.assert_allclose(a.K_cov, np.eye(4) * 64.0)
        assert c.fallback is None and "map" in c.timings_us
        assert c.reprojection_error_px <= a.reprojection_error_px + 1e-9
        assert np.all(np.linalg.eigvalsh(c.K_cov) > 0) and np.all(np.diag(c.K_cov) < 64.0)
    batch = fused.rectify_batch(frames.points_2d[rig], frames.points_3d[rig], frames.valid[rig])
    one = [fused.rectify(frames.points_2d[b][frames.valid[b]], frames.points_3d[b][frames.valid[b]]) for b in rig]
    np.testing.assert_allclose(batch.K, [o.K for o in one], atol=1e-6)
    np.testing.assert_allclose(batch.K_cov, [o.K_cov for o in one], rtol=1e-6)


def test_batch_covariance_is_the_single_frame_covariance_of_the_inference_points(tmp_path, map_model):
    frames, _ = map_model
    coef = np.array([[1.0, -0.3, 0.2, 0.5, 0.1]] * 4) * [[1.0], [1.1], [0.9], [1.2]]  # every statistic counts
    spec = replace(model_spec(frames), uncertainty=Uncertainty(coef=coef, correlation=np.eye(4)))
    rectifier = Rectifier.load(random_model_file(tmp_path / "stats.onnx", spec))
    for scene, infer in (("rig", frames.valid), ("natural", frames.infer_mask)):
        idx = np.flatnonzero(frames.scene == scene)[:3]
        batch = rectifier.rectify_batch(
            frames.points_2d[idx], frames.points_3d[idx], frames.valid[idx], infer_mask=infer[idx]
        )
        # K_cov depends on the inference points only: one frame of just those gives the same.
        one = [rectifier.rectify(frames.points_2d[b][infer[b]], frames.points_3d[b][infer[b]]) for b in idx]
        assert all(o.fallback is None for o in one) and not any(batch.fallback)
        np.testing.assert_allclose(batch.K_cov, [o.K_cov for o in one], rtol=1e-9)


def test_map_mode_needs_an_uncertainty_model(tmp_path, map_model):
    frames, _ = map_model
    old = random_model_file(tmp_path / "old.onnx", model_spec(frames))
    assert (
        Rectifier.load(old).rectify(*(a[0][frames.valid[0]] for a in (frames.points_2d, frames.points_3d))).K_cov
        is None
    )
    with pytest.raises(ModelError, match=r"old\.onnx.*no uncertainty model.*'map'"):
        Rectifier.load(old, mode="map")
    with pytest.raises(InputError, match="mode must be one of dimenet, map"):
        Rectifier.load(old, mode="fast")


def test_spec_round_trips_its_uncertainty_and_still_reads_1_0(map_model):
    frames, _ = map_model
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(3.0))
    back = ModelSpec.from_json(spec.to_json())
    np.testing.assert_array_equal(back.uncertainty.coef, spec.uncertainty.coef)
    old = json.loads(model_spec(frames).to_json())
    old["version"] = "1.0.0"
    assert ModelSpec.from_dict(old).uncertainty is None
    correlated = replace(
        spec, uncertainty=replace(spec.uncertainty, data_correlation=np.array([0, 0, 0.7, 0.5]), noise_scale_px=1.5)
    )
    back = ModelSpec.from_json(correlated.to_json()).uncertainty
    np.testing.assert_array_equal(back.data_correlation, [0, 0, 0.7, 0.5])
    assert back.noise_scale_px == 1.5
    v12 = json.loads(spec.to_json())  # spec 1.2: no data correlation, the posterior is not widened
    v12["version"] = "1.2.0"
    del v12["uncertainty"]["data_correlation"], v12["uncertainty"]["noise_scale_px"]
    np.testing.assert_array_equal(ModelSpec.from_dict(v12).uncertainty.data_correlation, np.zeros(4))


def test_evaluate_methods_json_and_table(map_model, tmp_path, capsys):
    frames, path = map_model
    data = write_dataset(frames, tmp_path / "d.npz")
    assert main(["evaluate", str(data), "--model", str(path), "--methods", "kc,self,dimenet,map,oracle", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    methods = out["methods"]
    assert list(methods) == ["kc", "self", "dimenet", "map", "oracle"]
    assert set(methods["map"]) == {"rig", "natural", "planar", "overall"}
    assert methods["kc"]["overall"]["rho"] == pytest.approx(0.0, abs=1e-12)
    assert methods["oracle"]["overall"]["rho"] == pytest.approx(1.0, abs=1e-12)
    assert methods["self"]["rig"]["rho"] > 0.95
    assert methods["dimenet"]["overall"]["avg_e"] == pytest.approx(out["overall"]["avg_e"])
    assert out["fallbacks"]["self"] >= 2  # the planar frames
    assert set(out["coverage"]) == {"dimenet", "map"} and set(out["coverage"]["map"]) == {"fx", "fy", "cx", "cy"}
    assert main(["evaluate", str(data), "--model", str(path), "--methods", "self,map"]) == 0
    assert "1-sigma coverage" in capsys.readouterr().out


def test_coverage_against_k_true_when_the_dataset_has_it(map_model):
    frames, path = map_model
    test = frames.select(frames.frames_in("test"))
    predictor = load_onnx_predictor(path)
    ev = evaluate(test, predictor.spec.K_c, predictor, methods=("dimenet",))
    pred = predictor.predict(test)
    ok = pred.predicted
    expected = coverage(k_params(pred.K[ok]), k_params(test.K_true[ok]), pred.cov[ok])
    assert ev.coverage_true == {"dimenet": expected}
    assert ev.coverage_true["dimenet"] != ev.coverage["dimenet"]  # K* is not K_true
    blind = evaluate(replace(test, K_true=None), predictor.spec.K_c, predictor, methods=("dimenet",))
    assert blind.coverage == ev.coverage and blind.coverage_true == {} and "coverage_true" not in blind.to_json()


def test_evaluate_methods_errors_exit_2(tmp_path, capsys):
    data = write_dataset(simulate("galaxy-s8", seed=1), tmp_path / "d.npz")
    for argv, message in ((["--methods", "map"], "needs --model"), (["--methods", "kc,fast"], "unknown method 'fast'")):
        assert main(["evaluate", str(data), *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1


def test_bench_map_mode_times_its_map_stage(map_model, capsys):
    _, path = map_model
    assert main(["bench", "--model", str(path), "--mode", "map", "--frames", "6", "--points", "64", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["mode"] == "map" and "map" in report["stages_us"] and report["ratio_p50"] > 0
