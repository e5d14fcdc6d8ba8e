"""The simulator's two options: lens distortion (points as the distorted image holds them, the
in-image rule through the lens) and the platform's K per frame (a simulated Hall-sensor
readout of the lens, from its own random stream); without them, datasets are as before."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.geometry import k_params, undistort_points
from dimenet.runtime.sim.family import family_member, family_profiles
from dimenet.runtime.sim.platform import LENS_POSITION_SIGMA_UM, MODEL, platform_sigma_px
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.simulator import lens_image, simulate

DIST = (0.08, -0.15, 0.0005, -0.0003, 0.05)  # a phone main camera's mild distortion (k1, k2, p1, p2, k3)
S8 = get_profile("galaxy-s8")
SMALL = replace(S8, n_train=10, n_test=6)
# The rig at ~1 m stays well inside the view, so the lens changes no point's visibility and the
# same seed draws the same photos with and without it.
FAR = replace(SMALL, distance_mm=(900.0, 1000.0))


def assert_same_arrays(a, b, skip=()):
    arrays_a, arrays_b = a.to_arrays(), b.to_arrays()
    assert set(arrays_a) - set(skip) == set(arrays_b) - set(skip)
    for key in set(arrays_a) - set(skip):
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key], err_msg=key)


def test_undistorting_the_distorted_dataset_gives_the_pinhole_simulation_of_the_same_seed():
    pinhole = simulate(FAR, seed=2, natural_frames=2, planar_frames=2)
    ds = simulate(FAR, seed=2, natural_frames=2, planar_frames=2, dist_coeffs=DIST)
    np.testing.assert_array_equal(ds.dist_coeffs, DIST)
    np.testing.assert_array_equal(ds.dist_K, FAR.nominal_K)
    assert_same_arrays(ds, pinhole, skip=("points_2d", "dist_coeffs", "dist_K"))  # K_true, masks, 3D, meta
    m = ds.valid
    assert np.abs(ds.points_2d[m] - pinhole.points_2d[m]).max() > 5.0
    back = undistort_points(ds.points_2d, ds.dist_K, ds.dist_coeffs)
    assert np.abs(back[m] - pinhole.points_2d[m]).max() < 1e-6
    assert np.abs(ds.undistorted().points_2d[m] - pinhole.points_2d[m]).max() < 1e-6


def test_the_in_image_rule_applies_to_the_distorted_pixels():
    """Pincushion distortion pushes corners outward: boards the pinhole camera sees are lost, and
    every point kept lies inside the image as the distorted photo holds it."""
    pinhole = simulate(SMALL, seed=1)
    ds = simulate(SMALL, seed=1, dist_coeffs=(0.3, 0.0, 0.0, 0.0))
    width, height = ds.image_size
    seen = ds.points_2d[ds.valid]
    assert np.all((seen >= 0) & (seen <= [width - 1, height - 1]))
    assert ds.valid.sum(1).mean() < pinhole.valid.sum(1).mean()
    # Barrel distortion (k1 < 0) folds back beyond a radius: pixels there are no image of the lens.
    f, (cx, cy) = S8.focal_px, S8.centre_px
    radius = np.array([0.5, 0.8, 1.2, 1.5])  # normalised; k1 = -0.3 folds at 1 / sqrt(0.9) = 1.05
    pinhole_px = np.c_[cx + f * radius, np.full(4, cy)]
    _, faithful = lens_image(pinhole_px, S8, np.array([-0.3, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(faithful, [True, True, False, False])


@pytest.mark.parametrize("bad", [(0.1, 0.2), (0.1, 0.0, 0.0, np.nan), (2e3, 0.0, 0.0, 0.0), "k1"])
def test_bad_distortion_is_an_input_error(bad):
    with pytest.raises(InputError, match="dist_coeffs"):
        simulate(SMALL, dist_coeffs=bad)


def test_datasets_without_the_options_are_unchanged():
    plain = simulate(SMALL, seed=3, natural_frames=2, planar_frames=1)
    off = simulate(SMALL, seed=3, natural_frames=2, planar_frames=1, dist_coeffs=None, platform_k=False)
    assert_same_arrays(off, plain)
    with_platform = simulate(SMALL, seed=3, natural_frames=2, planar_frames=1, platform_k=True)
    assert_same_arrays(with_platform, plain, skip=("K_platform", "meta"))
    assert {k: v for k, v in with_platform.meta.items() if k != "platform_k"} == plain.meta
    assert "platform_k" not in plain.meta and plain.K_platform is None and plain.dist_coeffs is None
    camera = family_profiles(1, 5, frames=(4, 2))[0]
    assert_same_arrays(
        family_member(camera, 0, 5, 1, platform_k=True), family_member(camera, 0, 5, 1), ("K_platform", "meta")
    )


def test_platform_k_errs_as_stated():
    """K_platform - K_true: zero mean, the stated sigma per parameter (lens position 1 um over the
    1.4 um pitch), fy's error fx's times the aspect, independent axes; deterministic per seed."""
    profile = replace(S8, n_train=1200, n_test=1, pixel_aspect=1.004)
    ds = simulate(profile, seed=0, platform_k=True)
    error = k_params(ds.K_platform) - k_params(ds.K_true)  # (F, 4) px: fx, fy, cx, cy
    sigma = platform_sigma_px(profile)
    np.testing.assert_allclose(sigma, LENS_POSITION_SIGMA_UM / 1.4 * np.array([1, 1.004, 1, 1]))
    np.testing.assert_allclose(error.std(0), sigma, rtol=0.08)  # 1201 draws: the std's own spread is 2 %
    assert np.all(np.abs(error.mean(0)) < 4 * sigma / np.sqrt(len(error)))
    np.testing.assert_allclose(error[:, 1], error[:, 0] * 1.004, atol=1e-9)
    corr = np.corrcoef(error[:, [0, 2, 3]].T)
    assert np.all(np.abs(corr[np.triu_indices(3, 1)]) < 0.1)
    np.testing.assert_array_equal(ds.K_platform[:, 2], ds.K_true[:, 2])  # still pinhole matrices
    stated = ds.meta["platform_k"]
    assert stated["simulated"] is True and stated["model"] == MODEL
    assert stated["sigma_px"] == pytest.approx(sigma.tolist())
    np.testing.assert_array_equal(simulate(profile, seed=0, platform_k=True).K_platform, ds.K_platform)
    assert not np.allclose(simulate(profile, seed=1, platform_k=True).K_platform[:5], ds.K_platform[:5])


def test_cli_simulate_with_distortion_and_platform_k(tmp_path, capsys):
    out = tmp_path / "s8.npz"
    args = ["simulate", "--profile", "galaxy-s8", "--seed", "1", "--out", str(out), "--platform-k"]
    assert main([*args, "--dist-coeffs=-0.05,0.02,0,0"]) == 0
    assert "lens distortion -0.05,0.02,0,0, K_platform" in capsys.readouterr().out
    ds = read_dataset(out)
    np.testing.assert_array_equal(ds.dist_coeffs, [-0.05, 0.02, 0.0, 0.0])
    assert ds.K_platform.shape == (ds.n_frames, 3, 3) and ds.meta["platform_k"]["model"] == MODEL
    assert main([*args, "--dist-coeffs", "0.1,0.2,0.3"]) == 2
    assert "dist_coeffs must be 4/5/8/12/14 numbers" in capsys.readouterr().err
