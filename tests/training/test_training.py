"""Trainer, model and run directory: real behaviour on small simulated datasets."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")  # the base-only install has no torch: skip, not fail

from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.evaluation.methods import evaluate
from dimenet.runtime.evaluation.predictor import load_predictor
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.formats.rig import paper_rig
from dimenet.runtime.geometry import k_params
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.sim.profiles import PROFILES
from dimenet.runtime.sim.simulator import simulate
from dimenet.training.model import DimeNet
from dimenet.training.run_dir import load_run
from dimenet.training.trainer import TrainConfig, focal_loss, train
from dimenet.training.units import (
    cluster_inference_points,
    frame_truth,
    one_plane_share,
    resynthesise,
    split_train_val,
    training_unit,
)

SMALL = dataclasses.replace(PROFILES["galaxy-s8"], name="small-s8", n_train=30, n_test=8)


@pytest.fixture(scope="module")
def small():
    return simulate(SMALL, seed=3)


def test_zero_feature_gives_exactly_zero_delta_k():
    model = DimeNet(240)
    torch.nn.init.normal_(model.fc1.weight, std=1.0)
    out = model(torch.zeros(3, 240))
    assert torch.equal(out, torch.zeros(3, 4))
    assert model(torch.ones(1, 240)).abs().sum() > 0


def test_training_is_deterministic_and_improves_on_k_c(small, tmp_path):
    cfg = TrainConfig(epochs=25, seed=5, patience=100)
    a = train(small, cfg, tmp_path / "a")
    b = train(small, cfg, tmp_path / "b")
    ma, _ = load_run(a.run_dir)
    mb, _ = load_run(b.run_dir)
    for (ka, va), (kb, vb) in zip(ma.state_dict().items(), mb.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)
    hist = a.history
    assert hist[-1]["train_mse_px2"] < hist[0]["train_mse_px2"]
    pred = load_predictor(a.run_dir)
    test = small.select(small.frames_in("test"))
    ev = evaluate(test, pred.spec.K_c, pred.predict_k)
    assert ev.overall.avg_e < ev.overall.avg_e_c  # better than the fixed K_c already
    for name in ("weights.safetensors", "spec.json", "history.json", "curve.png"):
        assert (a.run_dir / name).stat().st_size > 0
    spec = json.loads((a.run_dir / "spec.json").read_text())
    assert spec["format"] == "dimenet-model/1" and spec["provenance"]["seed"] == 5
    # The uncertainty model is fitted on the early-stopping frames: 68 % within 1 sigma there.
    assert pred.spec.uncertainty is not None
    for share in spec["provenance"]["uncertainty_val_coverage"].values():
        assert abs(share - 0.6827) < 0.03
    assert pred.predict(test).K_cov.shape == (test.n_frames, 4, 4)


def test_focal_loss_hand_computed():
    delta_k = torch.tensor([[1.0, 2.0, 30.0, 40.0], [5.0, 6.0, -7.0, 8.0]], requires_grad=True)
    target = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    loss = focal_loss(delta_k, target)
    assert loss.item() == pytest.approx((1 + 4 + 16 + 25) / 4)  # principal points play no part
    loss.backward()
    np.testing.assert_allclose(delta_k.grad.numpy(), [[0.5, 1.0, 0, 0], [2.0, 2.5, 0, 0]])


def test_focal_term_teaches_the_net_focus_breathing(small, tmp_path):
    """L_rep alone is nearly flat along f: the net's f ignores the frame's own (here 9.7 px rms
    off K*, uncorrelated); with the focal term it follows K* (3.0 px, correlation 0.76)."""
    train_frames = small.frames_in("train")
    f_star = k_params(calibrate_dataset(small).K_star[train_frames])[:, :2]
    errors, corr = {}, {}
    for weight in (0.0, TrainConfig().focal_weight):
        run = train(small, TrainConfig(epochs=25, seed=5, focal_weight=weight), tmp_path / str(weight)).run_dir
        f = k_params(load_predictor(run).predict_k(small.select(train_frames)))[:, :2]
        errors[weight] = np.sqrt(np.mean((f - f_star) ** 2))
        corr[weight] = np.corrcoef(f[:, 0], f_star[:, 0])[0, 1]
    with_term = TrainConfig().focal_weight
    assert errors[with_term] < 0.5 * errors[0.0] and corr[with_term] > 0.5 > corr[0.0]


@pytest.fixture(scope="module")
def fitting(small, tmp_path_factory):
    """A briefly trained run on ``small`` and what its uncertainty fit reads: (run dir, model,
    spec, early-stopping frames, the training unit holding them and their calibration)."""
    run = train(small, TrainConfig(epochs=2, seed=5), tmp_path_factory.mktemp("fitting") / "run").run_dir
    model, spec = load_run(run)
    _, val_idx = split_train_val(small, TrainConfig())
    unit = training_unit(small, TrainConfig(), None, "small")
    np.testing.assert_array_equal(unit.val.points_2d, small.select(val_idx).points_2d)
    return run, model, spec, unit.val, unit


def test_uncertainty_is_fitted_on_two_object_draws_too(fitting, monkeypatch):
    """As many two-object draws (hand-labelled natural features) as augmentation draws, each
    of all the early-stopping frames, with a 2-8 px label noise on each."""
    from dimenet.training import uncertainty as network_uncertainty

    _, model, spec, val, unit = fitting
    drawn, noise = [], {}  # the two-object draws; the 2D noise std added to each dataset, by id
    two_objects, add_noise = network_uncertainty.two_objects, network_uncertainty.add_noise

    def drawing(ds, rng):
        drawn.append(two_objects(ds, rng))
        return drawn[-1]

    def noising(ds, sigma_2d_px, sigma_3d_mm, rng):
        noise[id(ds)] = sigma_2d_px
        return add_noise(ds, sigma_2d_px, sigma_3d_mm, rng)

    monkeypatch.setattr(network_uncertainty, "two_objects", drawing)
    monkeypatch.setattr(network_uncertainty, "add_noise", noising)
    network_uncertainty.fit_network_uncertainty(model, spec, [unit], TrainConfig(), np.random.default_rng(0))
    assert len(drawn) == max(8, -(-network_uncertainty.UNCERTAINTY_SAMPLES // val.n_frames))
    for ds in drawn:
        assert ds.n_frames == val.n_frames and np.all(ds.infer_mask.sum(1) <= 100)
        assert np.all((2.0 <= noise[id(ds)]) & (noise[id(ds)] <= 8.0))


def test_data_correlation_is_fitted_on_the_map_estimates_of_the_noisy_draws(fitting, monkeypatch):
    """Only the augmentation and two-object draws, whose added noise their reference K' does
    not know, enter the fit; its result is what the model carries."""
    from dimenet.training import uncertainty as network_uncertainty

    _, model, spec, val, unit = fitting
    seen = {}

    def spy(errors, sigma, ratio, noise):
        seen.update(errors=errors, sigma=sigma, ratio=ratio, noise=noise)
        return np.array([0.0, 0.1, 0.2, 0.3])

    monkeypatch.setattr(network_uncertainty, "fit_data_correlation", spy)
    uncertainty, _ = network_uncertainty.fit_network_uncertainty(
        model, spec, [unit], TrainConfig(), np.random.default_rng(0)
    )
    np.testing.assert_array_equal(uncertainty.data_correlation, [0.0, 0.1, 0.2, 0.3])
    draws = max(8, -(-network_uncertainty.UNCERTAINTY_SAMPLES // val.n_frames))
    assert 0.9 * 2 * draws * val.n_frames <= len(seen["noise"]) <= 2 * draws * val.n_frames
    # The clean frames' noise is the corners' 0.36 px; the noisy draws add 0-3 and 2-8 px.
    assert np.median(seen["noise"]) > 1.5
    assert np.all((seen["ratio"] > 0) & (seen["ratio"] <= 1 + 1e-9)) and np.all(seen["sigma"] > 0)


def test_resynthesis_keeps_frames_when_share_is_zero_and_moves_only_the_principal_point(small):
    cal = calibrate_dataset(small)
    idx = np.flatnonzero(small.frames_in("train"))
    frames = small.select(idx)
    truth = frame_truth(frames, cal.K_star[idx], cal.rvec[idx], cal.tvec[idx], None)
    same, K_same = resynthesise(frames, truth, np.random.default_rng(0), share=0.0)
    np.testing.assert_allclose(same.points_2d[frames.valid], frames.points_2d[frames.valid], atol=1e-9)
    np.testing.assert_array_equal(K_same, cal.K_star[idx])
    moved, K_moved = resynthesise(frames, truth, np.random.default_rng(0), share=1.0)
    # Re-calibrating a re-imaged frame finds its own focal length and another frame's principal point.
    K_new = calibrate_dataset(dataclasses.replace(moved, split=np.full(moved.n_frames, "train"))).K_star
    p_old, p_new = k_params(cal.K_star[idx]), k_params(K_new)
    np.testing.assert_allclose(p_new[:, :2], p_old[:, :2], atol=1e-4)
    candidates = p_old[:, 2:]
    dist = np.abs(p_new[:, None, 2:] - candidates[None]).max(-1).min(-1)
    assert np.all(dist < 1e-4)  # px: LM convergence, far below the ~50 px spread of principal points
    np.testing.assert_allclose(k_params(K_moved), p_new, atol=1e-4)  # the K it returns is the one imaged under


def test_uncertainty_is_fitted_on_re_imaged_frames_against_their_new_k(fitting, monkeypatch):
    """Every draw is made on the early-stopping frames re-imaged under other principal points,
    and its residuals are taken against the K each frame is then imaged under: a re-imaging
    whose K is off by 1000 px in cx makes the fitted sigma of cx about that large."""
    from dimenet.training import uncertainty as network_uncertainty

    run, model, spec, val, unit = fitting
    calls = []

    def shifted(frames, frame_truth_, rng, share):
        calls.append(share)
        reimaged, K = resynthesise(frames, frame_truth_, rng, share)
        K = K.copy()
        K[:, 0, 2] += 1000.0
        return reimaged, K

    monkeypatch.setattr(network_uncertainty, "resynthesise", shifted)
    uncertainty, _ = network_uncertainty.fit_network_uncertainty(
        model, spec, [unit], TrainConfig(), np.random.default_rng(0)
    )
    draws = max(8, -(-network_uncertainty.UNCERTAINTY_SAMPLES // val.n_frames))
    assert calls == [1.0] * (2 * draws + 3 * -(-draws // 3))  # one re-imaging of all frames per draw
    pred = load_predictor(str(run)).predict(val)
    sigma = uncertainty.sigma(pred.stats[pred.predicted])
    assert np.all(sigma[:, 2] > 300.0) and np.all(sigma[:, [0, 1, 3]] < 300.0)


def test_other_sensor_other_point_count_and_no_val_split_train_and_evaluate(tmp_path):
    hd = dataclasses.replace(
        PROFILES["galaxy-s8"], name="hd-cam", image_size_px=(1920, 1080), pixel_pitch_um=2.8, n_train=24, n_test=6
    )
    ds = simulate(hd, seed=1)
    keep = np.arange(0, ds.n_points, 2)  # other P: 160 points per frame
    ds = dataclasses.replace(
        ds,
        points_2d=ds.points_2d[:, keep],
        points_3d=ds.points_3d[:, keep],
        valid=ds.valid[:, keep],
        infer_mask=ds.infer_mask[:, keep],
    )
    assert not ds.frames_in("val").any()
    fit_idx, val_idx = split_train_val(ds, TrainConfig())
    assert len(val_idx) > 0 and not set(fit_idx) & set(val_idx)
    path = write_dataset(ds, tmp_path / "hd.npz")
    result = train(ds, TrainConfig(epochs=3, features=FeatureSpec(Grid(4, 3))), tmp_path / "run")
    # With patience, a run whose val error cannot improve (lr 0) stops after that many epochs.
    stuck = train(ds, TrainConfig(epochs=6, features=FeatureSpec(Grid(4, 3)), lr=0.0, patience=1), tmp_path / "stuck")
    assert stuck.best_epoch == 1 and len(stuck.history) == 2
    pred = load_predictor(result.run_dir)
    assert pred.spec.image_size == (1920, 1080) and pred.spec.features.size == 5 * 12
    K = pred.predict_k(ds.select(ds.frames_in("test")))
    assert K.shape == (6, 3, 3) and np.all(np.isfinite(K))
    assert path.exists()


def test_a_share_of_frames_keeps_the_inference_points_of_one_board_and_the_rest_all_theirs(small):
    """The paper rig's boards: a frame whose inference points shrink keeps exactly one board's corners (a plane);
    its valid points, which the loss reads, and its 2D points stay."""
    out = one_plane_share(small, 0.5, np.random.default_rng(0))
    board = paper_rig().board_of_point
    changed = np.any(out.infer_mask != small.infer_mask, 1)
    assert 0.25 * small.n_frames < changed.sum() < 0.75 * small.n_frames
    for f in np.flatnonzero(changed):
        assert len(np.unique(board[out.infer_mask[f]])) == 1 and not np.any(out.infer_mask[f] & ~small.infer_mask[f])
    np.testing.assert_array_equal(out.valid, small.valid)
    np.testing.assert_array_equal(out.points_2d, small.points_2d)
    rng = np.random.default_rng(1)
    assert one_plane_share(small, 0.0, rng) is small  # a share of 0 draws nothing: a training without it is as before
    assert rng.random() == np.random.default_rng(1).random()


def test_clustered_inference_points_are_compact_noisy_candidates_and_spare_other_frames(small):
    rng = np.random.default_rng(0)
    candidates = small.valid.copy()
    candidates[:, ::2] = False  # only odd points may become labels
    out = cluster_inference_points(small, candidates, 0.5, (40, 60), 6.0, rng)
    changed = np.any(out.infer_mask != small.infer_mask, 1)
    assert 0.2 * small.n_frames < changed.sum() < 0.8 * small.n_frames
    for f in range(small.n_frames):
        v = small.valid[f]
        moved = np.any(out.points_2d[f][v] != small.points_2d[f][v], -1)
        if not changed[f]:
            np.testing.assert_array_equal(out.points_2d[f][v], small.points_2d[f][v])
            continue
        infer = out.infer_mask[f]
        assert 40 <= infer.sum() <= 60 and not np.any(infer & ~candidates[f])
        np.testing.assert_array_equal(moved, infer[v])  # label noise on the kept points only
        # Clusters: for some one or two kept points as centres, every kept point lies nearer to
        # them than every candidate left out.
        x = small.points_2d[f]
        kept, out_ = x[infer], x[candidates[f] & ~infer]
        d_kept = np.linalg.norm(kept[:, None] - kept[None], axis=-1)  # (k, k)
        d_out = np.linalg.norm(out_[:, None] - kept[None], axis=-1)  # (o, k)
        r_kept = np.minimum(d_kept[:, :, None], d_kept[:, None, :]).max(0)  # (k, k) per centre pair
        r_out = np.minimum(d_out[:, :, None], d_out[:, None, :]).min(0)
        assert np.any(r_kept <= r_out)
    assert out.valid is small.valid or np.array_equal(out.valid, small.valid)


def test_train_command_passes_the_focal_weight_and_refuses_a_negative_one(small, tmp_path, capsys):
    from dimenet.runtime.cli.main import main

    data = write_dataset(small, tmp_path / "small.npz")
    assert main(["train", str(data), "--out", str(tmp_path / "run"), "--epochs", "2", "--focal-weight", "0"]) == 0
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    best = min(history, key=lambda h: h["val_e_px"])["epoch"]
    assert capsys.readouterr().out.startswith(f"trained 2 epochs, kept epoch {best} (best val Avg(e) ")
    spec = json.loads((tmp_path / "run" / "spec.json").read_text())
    assert spec["provenance"]["config"]["focal_weight"] == 0.0
    for bad in ("-1", "nan", "inf"):
        res = subprocess.run(
            [
                sys.executable,
                "-m",
                "dimenet.runtime.cli.main",
                "train",
                str(data),
                "--out",
                str(tmp_path / "bad"),
                "--focal-weight",
                bad,
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and "--focal-weight" in lines[0], res.stderr


def test_a_simulated_unit_knows_how_far_each_frame_s_own_fit_is_from_the_true_k(small):
    """k_bias = K* - K_true in the model's pixels: a few px on the simulator's rig (its K* is
    within ~1 px of the truth), scaled with the points onto a generic model's canonical camera;
    zeros for a capture, which has no K_true."""
    unit = training_unit(small, TrainConfig(), None, "small")
    fit_idx, val_idx = split_train_val(small, TrainConfig())
    cal = calibrate_dataset(small)
    np.testing.assert_allclose(
        unit.val_truth.k_bias, k_params(cal.K_star[val_idx]) - k_params(small.K_true[val_idx]), atol=1e-9
    )
    assert 0 < np.abs(unit.truth.k_bias).max() < 10.0
    canonical = training_unit(small, TrainConfig(), 1000.0, "small")
    scale = 1000.0 / cal.K_c[0, 0]
    np.testing.assert_allclose(canonical.truth.k_bias[:, :2], unit.truth.k_bias[:, :2] * scale, rtol=1e-6, atol=1e-6)
    capture = training_unit(dataclasses.replace(small, K_true=None), TrainConfig(), None, "capture")
    assert not capture.truth.k_bias.any() and not capture.val_truth.k_bias.any()


def test_uncertainty_residuals_are_taken_against_the_true_k(fitting, monkeypatch):
    """The same draws with every frame's own fit 500 px further from the truth in cx give
    residuals 500 px larger there and the same elsewhere: sigma covers what the frame's points
    get wrong, not only the network's distance from them."""
    from dimenet.training import uncertainty as network_uncertainty

    _, model, spec, _, unit = fitting
    seen = []
    fit = network_uncertainty.fit_uncertainty

    def spy(residuals, stats):
        seen.append(residuals)
        return fit(residuals, stats)

    monkeypatch.setattr(network_uncertainty, "fit_uncertainty", spy)
    shifted = dataclasses.replace(unit.val_truth, k_bias=unit.val_truth.k_bias + [0.0, 0.0, 500.0, 0.0])
    for u in (unit, dataclasses.replace(unit, val_truth=shifted)):
        network_uncertainty.fit_network_uncertainty(model, spec, [u], TrainConfig(), np.random.default_rng(0))
    np.testing.assert_allclose(seen[1] - seen[0], np.broadcast_to([0.0, 0.0, 500.0, 0.0], seen[0].shape), atol=1e-6)


def test_the_structure_limit_is_measured_on_frames_without_their_build_errors(small):
    """A smooth field added to every fitting frame's residuals (a sagging sheet) leaves the
    limit where it was: it is what OIS and the augmentation's noise make, not the rig's bends."""
    from dimenet.training.scene_limits import structure_limit

    cfg = TrainConfig()
    unit = training_unit(small, cfg, None, "small")
    x = unit.fit.points_2d / unit.fit.image_size - 0.5
    field = 40.0 * np.nan_to_num(x**2)  # px, up to 10 px at the corners
    bent = dataclasses.replace(unit, truth=dataclasses.replace(unit.truth, residual=unit.truth.residual + field))
    limits = [structure_limit([u], cfg, cfg.features.grid, np.random.default_rng(4)) for u in (unit, bent)]
    assert limits[0] == limits[1]


def test_the_structure_limit_does_not_read_the_chance_fits_of_a_few_noisy_labels(small, monkeypatch):
    """Every fitting frame cut to 30-40 noisily labelled points (6 px): their residuals fit the smooth
    field by chance, which set the limit by the draw's luck (0.5 to 4.4 px across seeds here); the
    limit reads frames of at least STRUCTURE_LIMIT_POINTS points, so these leave it at its floor."""
    from dimenet.runtime.rectify.checks import STRUCTURE_PX
    from dimenet.training import scene_limits

    cfg = TrainConfig(cluster_share=1.0, cluster_points=(30, 40), max_label_noise_px=6.0, full_share=0.0)
    unit = training_unit(small, cfg, None, "small")
    limit = lambda: scene_limits.structure_limit([unit], cfg, cfg.features.grid, np.random.default_rng(0))  # noqa: E731
    assert limit() == STRUCTURE_PX
    monkeypatch.setattr(scene_limits, "STRUCTURE_LIMIT_POINTS", 0)
    assert limit() > 2 * STRUCTURE_PX  # what they gave before
