"""A camera's image errors (``sim.image_errors``): residual lens, corner bias, JPEG noise, ChArUco detection."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from dimenet.runtime.geometry import project, solve_pnp_start, undistort_points
from dimenet.runtime.sim import image_errors as ie
from dimenet.runtime.sim.family import family_member, family_profiles
from dimenet.runtime.sim.image_errors import ImageErrors, draw_image_errors
from dimenet.runtime.sim.scene_geometry import rig_scene
from dimenet.runtime.sim.scenes import random_rig
from dimenet.runtime.sim.simulator import simulate, visible

NONE = ImageErrors(residual_k1=0.0, bias_px=0.0, jpeg_px=0.0, charuco_missing=None, seed=0)


def camera():
    return family_profiles(1, 3, frames=(6, 0))[0]


def test_the_residual_lens_moves_the_image_corner_by_its_drawn_peak_and_within_its_reach():
    profile = camera()
    w, h = profile.image_size_px
    (cx, cy), f = profile.centre_px, profile.focal_px
    for seed in range(20):
        errors = draw_image_errors(profile, np.random.default_rng(seed))
        corner = np.array([[cx + w / 2.0, cy + h / 2.0]])  # as far from the centre as the image's corner
        moved = float(np.linalg.norm(errors.lens(corner, profile) - corner))
        r = np.hypot(w, h) / 2.0 / f
        assert abs(moved - abs(errors.residual_k1) * r**3 * f) <= 0.02 * moved + 1e-9  # radial k1 r^3, to 1st order
        assert moved <= ie.RESIDUAL_LENS_PX * w / ie.REFERENCE_WIDTH_PX * 1.05
        assert moved <= errors.reach_px(profile)


def test_a_boards_bias_is_one_affine_field_and_the_jpeg_error_heavy_tailed_and_bounded():
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(8.0), np.arange(6.0)), -1).reshape(-1, 2) * 40.0 + 500.0
    group = np.zeros(len(grid), np.int64)
    labels = np.full(5, -1)
    pts = np.concatenate([grid, grid[:5] + 7.0])
    bias = replace(NONE, bias_px=0.3)
    offsets = []
    for _ in range(300):
        moved = bias.detection(pts, np.r_[group, labels], rng)
        assert np.array_equal(moved[len(grid) :], pts[len(grid) :])  # labelled features keep theirs
        d = moved[: len(grid)] - grid
        A = np.c_[grid, np.ones(len(grid))]
        fit = np.linalg.lstsq(A, d, rcond=None)[0]
        if np.all(np.abs(d) < ie.BIAS_CLIP * 0.3 - 1e-9):  # unclipped: exactly affine across the board
            assert np.allclose(A @ fit, d, atol=1e-9)
        offsets.append(d.mean(0))
    assert 0.2 < np.std(offsets) < 0.4  # one offset per board and frame, N(0, 0.3) px per axis
    jpeg = replace(NONE, jpeg_px=0.2)
    d = np.concatenate([jpeg.detection(grid, group, rng) - grid for _ in range(200)]).ravel()
    assert np.max(np.abs(d)) <= ie.JPEG_CLIP * 0.2 + 1e-12
    kurtosis = np.mean((d - d.mean()) ** 4) / np.var(d) ** 2
    assert kurtosis > 4.0  # a Gaussian's is 3: heavy tails


def test_a_charuco_board_is_seen_in_part_and_misses_corners():
    rig = random_rig(np.random.default_rng(1))
    scene = rig_scene(rig)
    charuco = replace(NONE, charuco_missing=0.15)
    rng = np.random.default_rng(0)
    seen = np.ones(len(scene.points), bool)
    missed = np.mean([charuco.missed(seen, scene.group, rng).mean() for _ in range(200)])
    assert 0.12 < missed < 0.18
    few = scene.group == 0
    seen_few = seen & ~(few & (np.cumsum(few) > ie.CHARUCO_MIN_CORNERS))  # board 0 left with 6 corners
    for _ in range(50):
        miss = charuco.missed(seen_few, scene.group, rng)
        kept = seen_few & ~miss
        assert np.count_nonzero(kept[few]) in (0, ie.CHARUCO_MIN_CORNERS)
    assert not NONE.missed(seen, scene.group, rng).any()
    # Half a board inside the image: plain boards are lost whole, a ChArUco board keeps its seen corners.
    profile = camera()
    K = profile.nominal_K
    rvec, tvec = np.zeros(3), np.array([0.0, 0.0, 600.0])
    board = scene.group == 0
    x0 = project(scene.points[board], K, rvec, tvec)[:, 0]
    shift = (profile.image_size_px[0] - 1 - np.median(x0)) * 600.0 / K[0, 0]  # its median corner at the right edge
    tvec[0] += shift
    _, plain = visible(scene, profile, K, rvec, tvec)
    _, part = visible(scene, profile, K, rvec, tvec, min_board_corners=ie.CHARUCO_MIN_CORNERS)
    assert not plain[board].any()
    assert 0 < np.count_nonzero(part[board]) < np.count_nonzero(board)


def test_simulate_with_image_errors_keeps_the_pinhole_k_and_its_points_through_the_residual_lens():
    """Only the lens drawn: undistorting a frame's points by it leaves the corner noise about the pinhole
    projection under K_true; without errors the frames are the simulator's as before."""
    profile = camera()
    rig = random_rig(np.random.default_rng(2))
    lens = replace(NONE, residual_k1=0.03, seed=5)
    plain = simulate(profile, seed=3, rig=rig)
    ds = simulate(profile, seed=3, rig=rig, image_errors=lens)
    assert ds.meta["image_errors"]["residual_k1"] == 0.03 and "image_errors" not in plain.meta
    nothing = simulate(profile, seed=3, rig=rig, image_errors=NONE)
    assert np.array_equal(nothing.points_2d, plain.points_2d, equal_nan=True)
    nominal = profile.nominal_K
    for k in range(ds.n_frames):
        v = ds.valid[k]
        x = ds.points_2d[k, v]
        K = ds.K_true[k]
        rvec, tvec = solve_pnp_start(x, ds.points_3d[k, v], K)
        raw = np.linalg.norm(project(ds.points_3d[k, v], K, rvec, tvec) - x, axis=1).mean()
        back = undistort_points(x, nominal, np.array([0.03, 0.0, 0.0, 0.0]))
        rvec, tvec = solve_pnp_start(back, ds.points_3d[k, v], K)
        clean = np.linalg.norm(project(ds.points_3d[k, v], K, rvec, tvec) - back, axis=1).mean()
        assert clean < 2.0 * profile.corner_sigma_px < 2.0 * clean < raw
    w, h = profile.image_size_px
    inside = (ds.points_2d[..., 0] >= 0) & (ds.points_2d[..., 0] <= w - 1) & (ds.points_2d[..., 1] <= h - 1)
    assert inside[ds.valid].all()


def test_a_random_scene_family_draws_each_camera_its_image_errors_and_some_charuco_rigs():
    n = 12
    drawn = []
    for i, profile in enumerate(family_profiles(n, 4, frames=(3, 1))):
        ds = family_member(profile, i, 4, n, scenes="random")
        drawn.append(ds.meta["image_errors"])
        e = ds.meta["image_errors"]
        assert 0.0 <= e["bias_px"] <= ie.CORNER_BIAS_PX and 0.0 <= e["jpeg_px"] <= ie.JPEG_PX
        again = family_member(profile, i, 4, n, scenes="random")
        assert np.array_equal(again.points_2d, ds.points_2d, equal_nan=True)
        assert "image_errors" not in family_member(profile, i, 4, n, scenes="paper").meta
    assert len({e["seed"] for e in drawn}) == n
    assert any(e["charuco_missing"] is not None for e in drawn) and any(e["charuco_missing"] is None for e in drawn)
