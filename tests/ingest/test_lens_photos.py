"""Photos through a lens: `dimenet render --dist-coeffs` warps the pinhole picture through OpenCV's
distortion, `ingest` finds the bent boards, `calibrate --distortion` fits the lens with each
frame's K (the bundle), and `ingest --camera` puts a known lens into the dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dimenet.runtime.bench.ingest_score import score
from dimenet.runtime.cli.main import main
from dimenet.runtime.evaluation.calibration import read_calibration
from dimenet.runtime.formats.camera_file import write_camera
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import paper_rig
from dimenet.runtime.geometry import distort_points, k_params, project, undistort_points
from dimenet.runtime.rectify.user_camera import checked_camera
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, lens_warp, scaled_profile

LENS = (-0.11, 0.06, 0.0005, -0.0004)  # up to 40 px at the corners of a 1344 x 1008 photo
PROFILE = scaled_profile(get_profile("galaxy-s8"), 3.0)


@pytest.fixture(scope="module")
def lens_shots(tmp_path_factory):
    """Eight rendered 1344 x 1008 px photos through LENS, ingested as train frames."""
    folder = tmp_path_factory.mktemp("lens-shots")
    lens = ",".join(str(c) for c in LENS)
    argv = ["render", "--rig", "paper", "--profile", "galaxy-s8", "--n", "8", "--scale", "3", "--seed", "2"]
    assert main([*argv, f"--dist-coeffs={lens}", "--out", str(folder)]) == 0
    photos = sorted(str(p) for p in folder.glob("photo-*.jpg"))
    data = folder / "shots.npz"
    assert main(["ingest", *photos, "--rig", "paper", "--out", str(data), "--split", "train"]) == 0
    return folder, photos, read_truth(folder / TRUTH_FILE), data


def test_the_warp_is_the_lens_and_the_truth_its_distorted_corners(lens_shots):
    _, _, truth, _ = lens_shots
    np.testing.assert_array_equal(truth.dist_coeffs, LENS)
    K_lens = PROFILE.nominal_K
    np.testing.assert_allclose(truth.dist_K, K_lens)
    points = paper_rig().points()
    for k in range(len(truth.K)):
        pinhole = project(points, truth.K[k], truth.rvec[k], truth.tvec[k])
        np.testing.assert_allclose(truth.corners_px[k], distort_points(pinhole, K_lens, truth.dist_coeffs), atol=1e-9)
    warp = lens_warp(PROFILE, np.array(LENS))
    pixels = np.random.default_rng(0).uniform([0, 0], np.array(PROFILE.image_size_px) - 1, (500, 2))
    ix, iy = np.round(pixels).astype(int).T
    exact = undistort_points(np.c_[ix, iy].astype(float), K_lens, np.array(LENS)) + warp.margin
    np.testing.assert_allclose(np.c_[warp.map_x[iy, ix], warp.map_y[iy, ix]], exact, atol=2e-3)  # float32 maps


def test_photos_through_a_lens_are_ingested_and_their_lens_fitted(lens_shots, tmp_path, capsys):
    _, _, truth, data = lens_shots
    result = score(read_dataset(data), truth)
    assert result.boards_found == result.boards_shown and result.identity_errors == 0
    assert result.corner_rms_px <= 0.1 and result.k_error_px <= 0.2  # K* through the true lens
    assert main(["calibrate", str(data), "--out", str(tmp_path / "pinhole.npz")]) == 0
    assert main(["calibrate", str(data), "--out", str(tmp_path / "lens.npz"), "--distortion", "opencv4"]) == 0
    pinhole, lens = (read_calibration(tmp_path / f"{name}.npz") for name in ("pinhole", "lens"))
    error = np.abs(k_params(lens.K_star) - k_params(truth.K)).mean(0)
    # 0.69, 0.64, 1.52, 0.71 px: over 8 views the principal point trades a little with the tangential terms.
    assert error[:2].max() < 1.0 and error[2:].max() < 2.5
    assert np.abs(k_params(pinhole.K_star) - k_params(truth.K)).mean() > 20 * error.max()  # the lens ignored
    assert np.abs(lens.dist_coeffs[:2] - LENS[:2]).max() < 0.01


def test_ingest_camera_puts_a_known_lens_into_the_dataset_and_its_report(lens_shots, tmp_path, capsys):
    folder, photos, truth, _ = lens_shots
    camera = checked_camera(PROFILE.nominal_K, PROFILE.image_size_px, "test", np.array(LENS))
    cam = write_camera(tmp_path / "cam.yaml", camera, "opencv-yaml")
    data = tmp_path / "with-lens.npz"
    argv = ["ingest", *photos, "--rig", "paper", "--split", "train"]
    assert main([*argv, "--out", str(data), "--camera", str(cam)]) == 0
    assert f"lens: 4 distortion coefficients from {cam}" in capsys.readouterr().out
    ds = read_dataset(data)
    np.testing.assert_allclose(ds.dist_coeffs, LENS, atol=1e-12)
    np.testing.assert_allclose(ds.dist_K, PROFILE.nominal_K, atol=1e-9)
    # The report's K per photo is the pinhole camera's, as calibrate's K* under the dataset's lens.
    assert main(["calibrate", str(data), "--out", str(tmp_path / "cal.npz")]) == 0
    cal = read_calibration(tmp_path / "cal.npz")
    assert np.abs(k_params(cal.K_star) - k_params(truth.K)).mean() <= 0.2
    with_lens = json.loads((tmp_path / "with-lens.report.json").read_text())["photos"]
    reported = {p["photo"]: p["K_px"] for p in with_lens}  # rounded to 0.01 px
    np.testing.assert_allclose([reported[str(f)] for f in ds.frame_id], k_params(cal.K_star), atol=0.006)
    without = json.loads((folder / "shots.report.json").read_text())["photos"]
    assert np.mean([p["rms_px"] for p in without]) > 3 * np.mean([p["rms_px"] for p in with_lens])
    # A camera of another image size: every photo skipped with why, no dataset.
    half = checked_camera(PROFILE.nominal_K / 2 + np.diag([0, 0, 0.5]), (672, 504), "test", np.array(LENS))
    wrong = write_camera(tmp_path / "half.json", half, "json")
    capsys.readouterr()
    assert main([*argv, "--out", str(tmp_path / "no.npz"), "--camera", str(wrong)]) == 2
    out, err = capsys.readouterr()
    assert err.strip().count("\n") == 0 and "no photo gave a frame" in err
    assert "skipped: 1344x1008 px, the camera's image is 672x504 px" in out
    assert not (tmp_path / "no.npz").exists()
