"""`--camera FILE` and the dataset's own camera for `dimenet rectify` and `dimenet evaluate`:
the generic default serves any camera given, reports the K_c it used, and says what it needs."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
from helpers import DEVICE_MODEL, example_camera

from dimenet.runtime.assets import asset
from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.rectify.rectifier import DEFAULT_MODEL


def write_camera(path, K, size):
    path.write_text(json.dumps({"K": np.asarray(K).tolist(), "image_size": list(size)}))
    return path


def half_frames(frames):
    """The frames at half resolution (OpenCV's pixel convention)."""
    p2 = np.where(frames.valid[..., None], (frames.points_2d + 0.5) / 2 - 0.5, np.nan)
    return replace(frames, points_2d=p2, image_size=frames.image_size // 2)


def test_rectify_serves_the_camera_file_and_reports_its_k_c(frames, tmp_path, capsys):
    camera = example_camera()
    test = frames.select(frames.frames_in("test"))
    write_dataset(test, tmp_path / "test.npz")
    cam = write_camera(tmp_path / "cam.json", camera.K, camera.image_size)
    assert main(["rectify", str(tmp_path / "test.npz"), "--camera", str(cam), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["K_c"] == k_params(camera.K).tolist() and report["image_size"] == [4032, 3024]
    # Without a camera and without a train split to calibrate one, the generic model says what it needs.
    assert main(["rectify", str(tmp_path / "test.npz")]) == 2
    assert "give --camera FILE" in capsys.readouterr().err
    # A camera of another size than the dataset's images is refused in one line.
    other = write_camera(tmp_path / "other.json", camera.K, (2016, 1512))
    assert main(["rectify", str(tmp_path / "test.npz"), "--camera", str(other)]) == 2
    assert "the dataset's images 4032x3024" in capsys.readouterr().err


def test_evaluate_calibrates_the_dataset_camera_for_a_generic_model(frames, tmp_path, capsys):
    write_dataset(frames, tmp_path / "frames.npz")
    model = str(asset(DEFAULT_MODEL))
    assert main(["evaluate", str(tmp_path / "frames.npz"), "--model", model, "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["overall"]["rho"] > 0.5
    # At half resolution, with the half-resolution camera from its own train split, rho is the same.
    write_dataset(half_frames(frames), tmp_path / "half.npz")
    assert main(["evaluate", str(tmp_path / "half.npz"), "--model", model, "--json"]) == 0
    half = json.loads(capsys.readouterr().out)
    assert abs(half["overall"]["rho"] - ev["overall"]["rho"]) < 0.02
    np.testing.assert_allclose(np.array(half["K_c"])[:2, :2] * 2, np.array(ev["K_c"])[:2, :2], rtol=1e-3)


def test_a_device_model_serves_a_rescale_of_its_camera_and_refuses_another(frames, tmp_path, capsys):
    write_dataset(half_frames(frames), tmp_path / "half.npz")
    argv = ["rectify", str(tmp_path / "half.npz"), "--model", str(DEVICE_MODEL), "--json"]
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["image_size"] == [2016, 1512] and report["summary"]["avg_e_px"] < report["summary"]["avg_e_c_px"]
    camera = example_camera()
    wide = camera.K.copy()
    wide[:2, :2] *= 0.8  # another lens
    cam = write_camera(tmp_path / "wide.json", wide, camera.image_size)
    write_dataset(frames, tmp_path / "full.npz")
    assert main(["rectify", str(tmp_path / "full.npz"), "--model", str(DEVICE_MODEL), "--camera", str(cam)]) == 2
    assert "no rescale or crop of the model's" in capsys.readouterr().err
