"""`--camera FILE` and the dataset's own camera for `dimenet rectify` and `dimenet evaluate`:
the generic default serves any camera given, reports the K_c it used, and says what it needs;
`dimenet calibrate --camera-out` writes a camera file in any format that `--camera` reads back."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
from helpers import DEVICE_MODEL, example_camera

from dimenet.runtime.assets import asset
from dimenet.runtime.cli.main import main
from dimenet.runtime.evaluation.calibration import read_calibration
from dimenet.runtime.formats.camera_file import read_camera
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.rectify.model import DEFAULT_MODEL


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
    half = np.array(camera.K, dtype=float)
    half[:2] *= 0.5
    half[:2, 2] -= 0.25  # the centre of the top-left pixel stays at (0, 0)
    other = write_camera(tmp_path / "other.json", half, (2016, 1512))
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


def test_calibrate_writes_a_camera_file_that_rectify_serves(frames, tmp_path, capsys):
    write_dataset(frames, tmp_path / "frames.npz")
    write_dataset(frames.select(frames.frames_in("test")), tmp_path / "test.npz")
    argv = ["calibrate", str(tmp_path / "frames.npz"), "--out", str(tmp_path / "cal.npz")]
    assert main([*argv, "--camera-out", str(tmp_path / "cam.yaml"), "--camera-format", "ros"]) == 0
    assert f"-> {tmp_path / 'cam.yaml'} (ros)" in capsys.readouterr().out
    K_c = read_calibration(tmp_path / "cal.npz").K_c
    camera = read_camera(tmp_path / "cam.yaml")
    np.testing.assert_array_equal(camera.K, K_c)
    assert camera.image_size == tuple(int(v) for v in frames.image_size) and camera.dist_coeffs is None
    assert main(["rectify", str(tmp_path / "test.npz"), "--camera", str(tmp_path / "cam.yaml"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["K_c"] == k_params(K_c).tolist()
    # The format from the suffix (a folder made for it): .cameramodel is mrcal's.
    assert main([*argv, "--camera-out", str(tmp_path / "models" / "cam.cameramodel")]) == 0
    assert "(mrcal)" in capsys.readouterr().out
    np.testing.assert_array_equal(read_camera(tmp_path / "models" / "cam.cameramodel").K, K_c)


def test_calibrate_refuses_a_camera_format_it_cannot_tell_before_calibrating(tmp_path, capsys):
    argv = ["calibrate", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "cal.npz")]
    assert main([*argv, "--camera-out", str(tmp_path / "cam.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cam.yaml: its suffix names no format, give --camera-format (opencv-yaml" in err
    assert main([*argv, "--camera-format", "colmap"]) == 2
    assert "--camera-format needs --camera-out FILE" in capsys.readouterr().err
    assert main([*argv, "--camera-out", str(tmp_path / "c.yaml"), "--camera-format", "yaml"]) == 2
    assert "invalid choice: 'yaml'" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_rectify_picks_one_camera_of_a_file_and_refuses_a_bad_file_in_one_line(frames, tmp_path, capsys):
    camera = example_camera()
    test = tmp_path / "test.npz"
    write_dataset(frames.select(frames.frames_in("test")), test)
    fx, fy, cx, cy = (float(v) for v in k_params(camera.K))
    colmap = tmp_path / "cameras.txt"
    colmap.write_text(
        "# Camera list with one line of data per camera:\n"
        "1 SIMPLE_RADIAL 3072 2304 2559.68 1536 1152 -0.0204997\n"
        f"2 PINHOLE 4032 3024 {fx!r} {fy!r} {cx + 0.5!r} {cy + 0.5!r}\n"
    )
    assert main(["rectify", str(test), "--camera", f"{colmap}#2", "--json"]) == 0
    np.testing.assert_allclose(json.loads(capsys.readouterr().out)["K_c"], k_params(camera.K), rtol=0, atol=1e-9)
    bad = tmp_path / "bad.yaml"
    bad.write_text("cam0:\n  camera_model: omni\n  intrinsics: [1, 2, 3, 4, 5]\n")
    for argv_camera, message in [
        (str(colmap), f"{colmap}: holds 2 cameras (1, 2): choose one as {colmap}#NAME"),
        (f"{colmap}#3", f"{colmap}: no camera '3' (it holds 1, 2)"),
        (str(bad), f"{bad}: cam0.camera_model 'omni' is not supported"),
    ]:
        assert main(["rectify", str(test), "--camera", argv_camera]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, err


def test_a_lens_goes_from_the_dataset_through_calibrate_to_a_camera_file_and_rectify(tmp_path, capsys):
    """A distorted simulated dataset: calibrate reports its lens and writes it into the camera
    file (about the file's K); rectify with that file gives the K of the dataset's own lens."""
    from dimenet.runtime.sim.simulator import simulate

    lens = [-0.1, 0.04, 0.0003, -0.0002]
    ds = simulate("galaxy-s8", seed=5, dist_coeffs=lens)
    write_dataset(ds, tmp_path / "lens.npz")
    write_dataset(ds.select(ds.frames_in("test")), tmp_path / "t.npz")
    argv = ["calibrate", str(tmp_path / "lens.npz"), "--out", str(tmp_path / "cal.npz")]
    assert main([*argv, "--camera-out", str(tmp_path / "cam.xml")]) == 0
    out = capsys.readouterr().out
    assert "lens (the dataset's): dist_coeffs" in out
    camera = read_camera(tmp_path / "cam.xml")
    np.testing.assert_allclose(camera.dist_coeffs, lens, atol=1e-12)
    np.testing.assert_allclose(camera.K, ds.dist_K, atol=1e-9)
    assert main(["rectify", str(tmp_path / "t.npz"), "--camera", str(tmp_path / "cam.xml"), "--json"]) == 0
    with_file = json.loads(capsys.readouterr().out)
    assert main(["rectify", str(tmp_path / "lens.npz"), "--json"]) == 0  # the dataset's own lens and K_c
    own = json.loads(capsys.readouterr().out)
    assert with_file["summary"]["avg_e_px"] < 1.0 and own["summary"]["avg_e_px"] < 1.0  # the lens is undone
    # Fitted instead: the lens is the fit's, said so.
    assert main([*argv, "--distortion", "opencv5", "--camera-out", str(tmp_path / "fit.json")]) == 0
    assert "lens (fitted, opencv5)" in capsys.readouterr().out
    assert len(read_camera(tmp_path / "fit.json").dist_coeffs) == 5


def test_evaluate_refuses_a_camera_of_another_size_than_the_dataset(frames, tmp_path, capsys):
    """`evaluate --camera` checks the size as `rectify` does, with or without a model (a 1080p
    camera on a 4032x3024 dataset once printed Avg(e_c) 190 px and exit 0)."""
    write_dataset(frames, tmp_path / "frames.npz")
    hd = write_camera(tmp_path / "hd.json", [[1500.0, 0, 959.5], [0, 1500.0, 539.5], [0, 0, 1]], (1920, 1080))
    for extra in ([], ["--model", str(asset(DEFAULT_MODEL))]):
        assert main(["evaluate", str(tmp_path / "frames.npz"), "--camera", str(hd), *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "hd.json: the camera is 1920x1080 px, the dataset's images 4032x3024" in err[0], err
