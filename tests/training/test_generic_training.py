"""Training across a camera family (a generic model), fine-tuning from a model's weights, and
--train-frames: the spec they write, and that the result serves cameras it was not trained on."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import K_TEST

pytest.importorskip("torch")
pytest.importorskip("onnx")

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import InputError
from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.evaluation.methods import evaluate
from dimenet.runtime.evaluation.predictor import load_predictor
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.rectify.encoders.data_step import STEP_SIZE
from dimenet.runtime.rectify.encoders.moments import MOMENT_SIZE
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.user_camera import Camera
from dimenet.runtime.sim.family import simulate_family
from dimenet.training.config import TrainConfig
from dimenet.training.init_weights import initial_weights
from dimenet.training.run_dir import load_run
from dimenet.training.trainer import FACTORY_C_WIDTH, FACTORY_F_REL, factory_k_c, train
from dimenet.training.units import first_train_frames


@pytest.fixture(scope="module")
def family():
    """Three small cameras of a family (16 train + 4 test rig frames each)."""
    return [ds for _, ds in simulate_family(3, 7, frames=(16, 4))]


@pytest.fixture(scope="module")
def generic_run(family, tmp_path_factory):
    return train(family[:2], TrainConfig(epochs=3, seed=1), tmp_path_factory.mktemp("generic") / "run")


def camera_of(ds):
    return Camera(calibrate_dataset(ds).K_c, tuple(int(v) for v in ds.image_size))


def test_a_family_trains_a_generic_model_that_serves_an_unseen_camera(family, generic_run):
    model, spec = load_run(generic_run.run_dir)
    assert spec.generic is not None and spec.K_c is None and spec.features.depth_mm is not None
    assert spec.provenance["cameras"] == [ds.meta["profile"] for ds in family[:2]]
    bounds = spec.generic.delta_bounds
    assert np.all(bounds[:, 0] < 0) and np.all(bounds[:, 1] > 0)
    assert spec.uncertainty is not None
    unseen = family[2]
    predictor = load_predictor(generic_run.run_dir).for_camera(camera_of(unseen))
    test = unseen.select(unseen.frames_in("test"))
    ev = evaluate(test, predictor.K_c, predictor, methods=("dimenet", "map"))
    assert ev.fallbacks["dimenet"] < test.n_frames and np.isfinite(ev.methods["map"]["overall"].avg_e)


def test_a_scene_encoder_trains_with_the_data_step_moments_and_factory_k_c(family, generic_run, tmp_path):
    """--data-step, --moments, --plane-share and --k-c-error 1 (every camera, every epoch, under a factory-like
    K_c): the spec says so, the plausible Delta K widens by the factory span either way, and the model serves an
    unseen camera."""
    config = TrainConfig(
        epochs=2, seed=1, features=FeatureSpec(data_step=True, moments=True), k_c_error=1.0, plane_share=0.2
    )
    run = train(family[:2], config, tmp_path / "run")
    _, spec = load_run(run.run_dir)
    assert spec.features.data_step and spec.features.moments
    assert spec.features.size == spec.features.grid_size + STEP_SIZE + MOMENT_SIZE
    plain = load_run(generic_run.run_dir)[1].generic.delta_bounds
    widened = spec.generic.delta_bounds
    f_span = FACTORY_F_REL * spec.generic.focal_px
    assert np.all(widened[:2, 0] <= -f_span) and np.all(widened[:2, 1] >= f_span)
    assert np.all(np.ptp(widened, 1) > np.ptp(plain, 1) + 2 * f_span * np.array([0.99, 0.99, 0.0, 0.0]))
    unseen = family[2]
    predictor = load_predictor(run.run_dir).for_camera(camera_of(unseen))
    test = unseen.select(unseen.frames_in("test"))
    assert np.all(np.isfinite(predictor.predict_k(test)))


def test_a_batch_without_a_pose_under_the_net_s_k_is_skipped_and_counted(family, tmp_path, monkeypatch):
    """A 40-minute training does not die on one frame whose pose the BPnP layer cannot find under the net's
    K, nor on a frame with no C0 pose under a drawn factory K_c: the batch gives no gradient, the frame sits
    the epoch out, and the epoch's history counts both."""
    from dimenet.training import trainer

    calls = {"n": 0}
    real = trainer.reprojection_loss

    def failing_first(delta_k, *args):
        calls["n"] += 1
        if calls["n"] == 1:
            raise InputError("frame 3: PnP did not converge (no isolated optimum in front of the camera)")
        return real(delta_k, *args)

    monkeypatch.setattr(trainer, "reprojection_loss", failing_first)
    real_poses = trainer.c0_poses

    def one_unposed_frame(points_2d, points_3d, mask, K_c):
        rvec, tvec, reasons = real_poses(points_2d, points_3d, mask, K_c)
        if len(reasons) > 5:  # a unit's fit frames (its val frames are 2 or 3)
            reasons[5] = "PnP failed: no camera pose explains these correspondences"
        return rvec, tvec, reasons

    monkeypatch.setattr(trainer, "c0_poses", one_unposed_frame)
    run = train(family[:2], TrainConfig(epochs=2, seed=1, k_c_error=1.0), tmp_path / "run")
    assert [h.get("skipped_batches", 0) for h in run.history] == [1, 0]
    assert [h.get("unposed_frames", 0) for h in run.history] == [2, 2]  # one per camera and epoch
    assert all(np.isfinite(h["val_e_px"]) for h in run.history)


def test_a_factory_k_c_is_off_within_its_ranges_and_keeps_the_pixel_aspect():
    camera = Camera(K_TEST.copy(), (4032, 3024))
    rng = np.random.default_rng(0)
    k = np.array([k_params(factory_k_c(camera, rng)) for _ in range(400)])
    k0 = k_params(K_TEST)
    scale = k[:, 0] / k0[0]
    assert np.all(np.abs(scale - 1) <= FACTORY_F_REL) and np.ptp(scale) > FACTORY_F_REL  # drawn across the range
    np.testing.assert_allclose(k[:, 1] / k0[1], scale)  # one factor: fy / fx as calibrated
    shift = np.abs(k[:, 2:] - k0[2:]) / 4032
    assert np.all(shift <= FACTORY_C_WIDTH) and shift.max() > 0.9 * FACTORY_C_WIDTH


def test_train_frames_keeps_the_first_n_train_frames_in_file_order(family):
    ds = family[0]
    kept = first_train_frames(ds, 5)
    train_ids = ds.frame_id[ds.frames_in("train")]
    assert list(kept.frame_id[kept.frames_in("train")]) == list(train_ids[:5])
    assert kept.frames_in("test").sum() == ds.frames_in("test").sum()
    with pytest.raises(ValueError, match="more than the 16 train frames"):
        first_train_frames(ds, 17)


def test_fine_tuning_starts_from_the_init_weights_and_keeps_a_generic_model_generic(family, generic_run, tmp_path):
    init = initial_weights(str(generic_run.run_dir))
    run = train(family[2], TrainConfig(epochs=1, seed=2, train_frames=8), tmp_path / "tuned", init=init)
    model, spec = load_run(run.run_dir)
    assert spec.generic is not None and spec.provenance["init"] == str(generic_run.run_dir)
    assert spec.provenance["cameras"] == [family[2].meta["profile"]]
    # One epoch of AdamW moves the weights, but only a little from where they started.
    start = init.state_dict["fc1.weight"]
    moved = (model.state_dict()["fc1.weight"] - start).norm() / start.norm()
    assert 0 < float(moved) < 0.2


def test_the_train_command_reads_a_family_folder_and_fine_tunes(family, tmp_path, capsys):
    folder = tmp_path / "family"
    folder.mkdir()
    for ds in family[:2]:
        write_dataset(ds, folder / f"{ds.meta['profile']}.npz")
    assert main(["train", str(folder), "--out", str(tmp_path / "g"), "--epochs", "1"]) == 0
    assert load_run(tmp_path / "g")[1].generic is not None
    data = tmp_path / "one.npz"
    write_dataset(family[2], data)
    argv = ["train", str(data), "--out", str(tmp_path / "t"), "--epochs", "1", "--init", str(tmp_path / "g")]
    assert main([*argv, "--train-frames", "6"]) == 0
    spec = load_run(tmp_path / "t")[1]
    assert spec.generic is not None and spec.provenance["config"]["train_frames"] == 6
    # The bundled any-scene model fine-tunes with its encoder (the step, the moments, the gated head) kept.
    argv = ["train", str(data), "--out", str(tmp_path / "a"), "--epochs", "1", "--init", "any-scene"]
    assert main([*argv, "--train-frames", "6"]) == 0
    tuned = load_run(tmp_path / "a")[1]
    assert tuned.provenance["init"] == "any-scene" and tuned.head == "gated_step"
    assert tuned.features.data_step and tuned.features.moments
    capsys.readouterr()
    assert main(["train", str(tmp_path / "empty"), "--out", str(tmp_path / "x")]) == 2
    (tmp_path / "empty").mkdir()
    assert main(["train", str(tmp_path / "empty"), "--out", str(tmp_path / "x")]) == 2
    assert "without dataset files" in capsys.readouterr().err


def test_a_device_init_fine_tunes_one_dataset_not_a_family(family, tmp_path):
    from helpers import DEVICE_MODEL

    with pytest.raises(ValueError, match="is a device model: it fine-tunes on one dataset"):
        train(family[:2], TrainConfig(epochs=1), tmp_path / "x", init=initial_weights(str(DEVICE_MODEL)))
