"""The rectifier on a camera with lens distortion: the points are undistorted to the pinhole
camera of K_c, so K and the poses are those of the distortion-free frames, while e and e_c are
measured in the distorted image the points came from (checked against cv2.projectPoints)."""

from __future__ import annotations

import re
from dataclasses import replace

import cv2
import numpy as np
import pytest
from helpers import constant_uncertainty, model_spec
from test_rectifier_camera import linear_model, rig_frames

from dimenet.runtime.errors import CameraError, InputError
from dimenet.runtime.evaluation.calibration import calibrate_dataset, dataset_camera
from dimenet.runtime.evaluation.metrics import reduction_ratio
from dimenet.runtime.geometry import distort_points, mean_distorted_error, undistort_points
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera, checked_camera
from dimenet.runtime.sim.simulator import simulate

# A phone main camera's barrel distortion (k1, k2, p1, p2, k3): ~90 px at a 12 MP corner.
DIST = np.array([-0.12, 0.05, 0.0004, -0.0003, -0.01])


@pytest.fixture(scope="module")
def setup(frames):
    spec = replace(model_spec(frames), uncertainty=constant_uncertainty(3.0))
    model = linear_model(spec)
    camera = Camera(spec.K_c, tuple(spec.image_size))
    p2, p3, valid = rig_frames(frames)
    distorted = np.where(valid[..., None], distort_points(p2, spec.K_c, DIST), np.nan)
    return model, camera, distorted, p2, p3, valid


def test_distort_and_undistort_are_inverse_to_a_nanometre_at_the_corners():
    K = np.array([[3000.0, 0, 2015.5], [0, 3000.0, 1511.5], [0, 0, 1]])
    corners = np.array([[0.0, 0.0], [4031, 0], [0, 3023], [4031, 3023], [2015.5, 1511.5], [np.nan, 1.0]])
    for dist in (DIST[:4], DIST, np.r_[DIST, 0.01, 0.0, 0.002], np.r_[DIST, 0, 0, 0, 1e-3, 0, 5e-4, 0]):
        there = distort_points(corners, K, dist)
        back = undistort_points(there, K, dist)
        np.testing.assert_allclose(back[:5], corners[:5], atol=1e-6)
        assert np.isnan(back[5]).all() and np.isnan(there[5]).all()
    reference = cv2.projectPoints(
        np.c_[(corners[:5] - K[:2, 2]) / 3000.0, np.ones(5)], np.zeros(3), np.zeros(3), K, DIST
    )[0].reshape(-1, 2)
    np.testing.assert_allclose(distort_points(corners[:5], K, DIST), reference, atol=1e-9)


@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_k_and_pose_are_the_pinhole_frames_and_errors_the_distorted_images(setup, mode):
    model, camera, distorted, p2, p3, valid = setup
    plain = Rectifier(model, mode, camera)
    lens = Rectifier(model, mode, Camera(camera.K, camera.image_size, DIST))
    for b in range(4):
        m = valid[b]
        want, got = plain.rectify(p2[b][m], p3[b][m]), lens.rectify(distorted[b][m], p3[b][m])
        np.testing.assert_allclose(got.K, want.K, atol=1e-6)
        np.testing.assert_allclose(got.tvec, want.tvec, atol=1e-6)
        assert (got.fallback is None) == (want.fallback is None)  # the reasons' errors: each image's own
        # e_c against OpenCV's own distorted projection under K_c and the C0 pose.
        _, rvec_c0, tvec_c0 = cv2.solvePnP(p3[b][m], p2[b][m], camera.K, None, flags=cv2.SOLVEPNP_SQPNP)
        image = cv2.projectPoints(p3[b][m], rvec_c0, tvec_c0, camera.K, DIST)[0].reshape(-1, 2)
        e_c = np.linalg.norm(image - distorted[b][m], axis=1).mean()
        assert got.reprojection_error_kc_px == pytest.approx(e_c, rel=1e-4)
        assert got.reprojection_error_kc_px != pytest.approx(want.reprojection_error_kc_px, rel=1e-3)
    batch = lens.rectify_batch(distorted, p3, valid)
    single = [lens.rectify(distorted[b][valid[b]], p3[b][valid[b]]) for b in range(len(p2))]
    np.testing.assert_allclose(batch.K, [s.K for s in single], atol=1e-9)
    np.testing.assert_allclose(batch.reprojection_error_px, [s.reprojection_error_px for s in single], rtol=1e-6)
    np.testing.assert_allclose(batch.reprojection_error_kc_px, [s.reprojection_error_kc_px for s in single], rtol=1e-6)


def test_distorted_points_without_their_distortion_are_worse(setup):
    model, camera, distorted, _, p3, valid = setup
    ignored = Rectifier(model, "dimenet", camera).rectify_batch(distorted, p3, valid)
    known = Rectifier(model, "dimenet", Camera(camera.K, camera.image_size, DIST)).rectify_batch(distorted, p3, valid)
    assert known.reprojection_error_kc_px.mean() < 0.5 * ignored.reprojection_error_kc_px.mean()


def test_bad_distortion_is_a_camera_error():
    K = np.array([[1000.0, 0, 500], [0, 1000.0, 400], [0, 0, 1]])
    for bad in ([0.1, 0.2, 0.0], [np.nan, 0, 0, 0], ["a", 0, 0, 0], [1e9, 0, 0, 0]):
        with pytest.raises(CameraError, match="dist_coeffs"):
            checked_camera(K, (1000, 800), "cam.yaml", bad)
    assert checked_camera(K, (1000, 800), "cam.yaml", [0, 0, 0, 0, 0]).dist_coeffs is None
    with pytest.raises(CameraError, match="give K_c"):
        Rectifier.load(dist_coeffs=DIST)


@pytest.mark.parametrize("lens", [[-0.12, 0.05, 0.0004, -0.0003, -0.01], [0.08, -0.03, 0.0, 0.0]])
def test_rho_on_distorted_frames_is_that_of_their_undistorted_twins(lens):
    """The bundled model on simulated galaxy-s8 test frames through a lens, against the same
    frames undistorted under a pinhole camera (e* in each one's own image): within 1 point."""
    ds = simulate("galaxy-s8", seed=0, dist_coeffs=lens, natural_frames=34)
    camera = dataset_camera(ds)
    pinhole = ds.undistorted()
    cal = calibrate_dataset(pinhole)
    p3 = np.where(ds.valid[..., None], ds.points_3d, 0.0)
    e_star_image = mean_distorted_error(ds.points_2d, p3, ds.valid, cal.K_star, cal.rvec, cal.tvec, ds.dist_K, lens)
    x = np.where(pinhole.valid[..., None], pinhole.points_2d, 0.0)
    inside = np.all((x >= -0.5) & (x <= np.array(camera.image_size) - 0.5), axis=(1, 2))  # the pinhole camera's image
    model = load_model()
    for scene in ("rig", "natural"):
        t = ds.frames_in("test") & (ds.scene == scene) & inside
        rho = []
        for frames, cam, e_star in (
            (ds, camera, e_star_image),
            (pinhole, Camera(camera.K, camera.image_size), cal.e_star),
        ):
            r = Rectifier(model, "dimenet", cam).rectify_batch(
                frames.points_2d[t], frames.points_3d[t], frames.valid[t], infer_mask=frames.infer_mask[t]
            )
            rho.append(
                reduction_ratio(r.reprojection_error_kc_px.mean(), r.reprojection_error_px.mean(), e_star[t].mean())
            )
        assert t.sum() >= 25 and abs(rho[0] - rho[1]) < 0.01, (scene, rho)


def _outcome(call, *args):
    """("fallback", the result's fallback: one, or a tuple per frame) or ("refused", the InputError's message)."""
    try:
        return "fallback", call(*args).fallback
    except InputError as exc:
        return "refused", str(exc)


def test_batch_and_single_agree_frame_by_frame_on_random_lenses(setup):
    """Issue 33: a lens whose undistortion is not finite for some points (p1 = p2 = 1, a rational
    k4 = 50, or random coefficients of 0.5) raised numpy's LinAlgError from rectify_batch; every lens
    now gives the single path's answer: its fallbacks, or its InputError naming the frame."""
    model, camera, _, p2, p3, valid = setup
    p2 = np.where(valid[..., None], p2, 0.0)
    rng = np.random.default_rng(4)
    lenses = [np.array([0.0, 0.0, 1.0, 1.0]), np.array([0.0, 0.0, 1.0, 1.0, 0.0, 50.0, 0.0, 0.0])]
    lenses += [rng.normal(0.0, rng.choice([0.05, 0.5]), rng.choice([4, 5, 8, 12, 14])) for _ in range(30)]
    refused = 0
    for dist in lenses:
        lens = Rectifier(model, "dimenet", Camera(camera.K, camera.image_size, dist))
        x, X, v = p2[:4], p3[:4], valid[:4]  # the photo's points, whatever the lens file says
        single = [_outcome(lens.rectify, x[b][v[b]], X[b][v[b]]) for b in range(len(x))]
        batch = _outcome(lens.rectify_batch, x, X, v)
        errors = [(b, message) for b, (kind, message) in enumerate(single) if kind == "refused"]
        if errors:  # the batch refuses with one refused frame's own message (its rules run rule by rule)
            refused += 1
            unindexed = [re.sub(r"point \d+ at", "point at", f"frame {b}: {message}") for b, message in errors]
            assert batch[0] == "refused"
            assert re.sub(r"point \d+ at", "point at", batch[1]) in unindexed  # a batch counts points along P
        else:
            assert batch == ("fallback", tuple(fallback for _, fallback in single))
    assert refused >= 2  # the two lenses with no inverse at these points, at least


def test_a_lens_without_an_inverse_at_the_points_is_one_line_from_dataset_rectify(tmp_path, capsys):
    from dimenet.runtime.cli.main import main
    from dimenet.runtime.formats.camera_file import write_camera
    from dimenet.runtime.formats.dataset import write_dataset

    ds = simulate("galaxy-s8", seed=1)
    write_dataset(ds, tmp_path / "s8.npz")
    cal = calibrate_dataset(ds)
    bad = checked_camera(cal.K_c, tuple(int(v) for v in ds.image_size), "test", [0, 0, 1.0, 1.0, 0, 50.0, 0, 0])
    write_camera(tmp_path / "cam.json", bad, "json")
    assert main(["rectify", str(tmp_path / "s8.npz"), "--camera", str(tmp_path / "cam.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "lens model has no inverse" in err and "Traceback" not in err
