import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import geometry as g
from dimenet.runtime.errors import InputError
from dimenet.runtime.json_text import JsonProblem
from dimenet.runtime.rectify.encoders.data_step import STEP_PRIOR_REL, STEP_SIZE
from dimenet.runtime.rectify.encoders.grid import CHANNELS
from dimenet.runtime.rectify.encoders.moments import MOMENT_SIZE
from dimenet.runtime.rectify.features import DEFAULT_SCALE, FeatureSpec, grid_features
from dimenet.runtime.rectify.grid import Grid

IMAGE = (4032, 3024)


def reference_features(p2, p3, mask, K_c, rvec, tvec, spec):
    """Per-point Python loop written from the paper's equations, to check the vectorised code."""
    u, v = spec.grid.cols, spec.grid.rows
    C = len(spec.channels)
    out = np.zeros((v, u, C))
    count = np.zeros((v, u))
    R = g.rvec_to_matrix(rvec)
    # Scale-free depth: the {C0} points scaled so that the inference points' mean depth is depth_mm.
    z_mean = np.mean([(R @ X + tvec)[2] for X, m in zip(p3, mask) if m])
    f = 1.0 if spec.depth_mm is None else spec.depth_mm / z_mean
    for x, X, m in zip(p2, p3, mask):
        if not m:
            continue
        Xc = R @ X + tvec
        proj = K_c @ (Xc / Xc[2])
        full = {"dx": proj[0] - x[0], "dy": proj[1] - x[1], "X": f * Xc[0], "Y": f * Xc[1], "inv_z": 1 / (f * Xc[2])}
        col = min(int(x[0] // (IMAGE[0] / u)), u - 1)
        row = min(int(x[1] // (IMAGE[1] / v)), v - 1)
        out[row, col] += [full[c] * spec.scale[c] for c in spec.channels]
        count[row, col] += 1
    out /= np.maximum(count, 1)[..., None]
    return out.reshape(-1)


@pytest.mark.parametrize("grid", [Grid(8, 6), Grid(1, 1)])  # one cell sums every point without a cell index
@pytest.mark.parametrize("depth_mm", [None, 500.0])
@pytest.mark.parametrize("variant", ["A", "B", "C", "D", "E"])
def test_vectorised_feature_equals_per_point_reference(variant, depth_mm, grid):
    rng = np.random.default_rng(0)
    x, X, K, rvec, tvec = random_frames(rng, frames=3, points=50, noise_px=2.0)
    mask = rng.random((3, 50)) > 0.3
    spec = FeatureSpec(grid=grid, variant=variant, depth_mm=depth_mm)
    K_c = K_TEST.copy()
    K_c[0, 2] += 12.0
    feats = grid_features(x, X, mask, K_c, IMAGE, spec, poses=(rvec, tvec))
    assert feats.shape == (3, spec.size)
    for b in range(3):
        np.testing.assert_allclose(
            feats[b], reference_features(x[b], X[b], mask[b], K_c, rvec[b], tvec[b], spec), atol=1e-10
        )


def test_layout_is_row_major_and_empty_cells_are_zero():
    # One point at pixel (1100, 600): column 2, row 1 of the 8x6 grid (504 px cells).
    K_c = K_TEST
    X = np.array([[[(1100 - 2016) / 3000 * 1000, (600 - 1512) / 3010 * 1000, 1000.0]] * 6])
    x = np.full((1, 6, 2), [1100.0, 600.0])
    x[0, 0] += [3.0, -1.0]
    spec = FeatureSpec()
    f = grid_features(x, X, np.ones((1, 6), bool), K_c, IMAGE, spec, poses=(np.zeros((1, 3)), np.zeros((1, 3))))
    cell = 1 * 8 + 2
    nonzero = np.flatnonzero(f[0])
    assert set(nonzero // 5) == {cell}
    np.testing.assert_allclose(
        f[0, cell * 5 : cell * 5 + 2], np.array([-3.0, 1.0]) / 6 * DEFAULT_SCALE["dx"], atol=1e-9
    )
    np.testing.assert_allclose(f[0, cell * 5 + 4], 500.0 / 1000.0)


def test_pmd_vanishes_when_k_c_is_the_true_k_and_pnp_is_solved():
    rng = np.random.default_rng(1)
    x, X, K, *_ = random_frames(rng, frames=2, points=60)
    f = grid_features(x, X, np.ones((2, 60), bool), K_TEST, IMAGE, FeatureSpec(variant="B"))
    assert np.abs(f).max() < 1e-6


def test_batch_equals_single_frames_and_masked_points_have_no_effect():
    rng = np.random.default_rng(2)
    x, X, *_ = random_frames(rng, frames=4, points=40, noise_px=1.0)
    mask = np.ones((4, 40), bool)
    mask[:, :5] = False
    spec = FeatureSpec()
    batch = grid_features(x, X, mask, K_TEST, IMAGE, spec)
    x2 = x.copy()
    x2[:, :5] = np.nan  # garbage on masked points
    for b in range(4):
        np.testing.assert_allclose(
            grid_features(x2[b : b + 1], X[b : b + 1], mask[b : b + 1], K_TEST, IMAGE, spec)[0], batch[b], atol=1e-9
        )


def test_scale_free_depth_one_frame_equals_the_batch_and_ignores_the_world_unit():
    """The one-frame float path of the depth factor equals the batch's array path, and 3D points
    in metres give the millimetres' feature."""
    rng = np.random.default_rng(3)
    x, X, *_ = random_frames(rng, frames=3, points=40, noise_px=1.0)
    spec = FeatureSpec(depth_mm=500.0)
    batch = grid_features(x, X, None, K_TEST, IMAGE, spec)
    for b in range(3):
        np.testing.assert_allclose(grid_features(x[b : b + 1], X[b : b + 1], None, K_TEST, IMAGE, spec)[0], batch[b])
    np.testing.assert_allclose(grid_features(x, X / 1000.0, None, K_TEST, IMAGE, spec), batch, atol=1e-9)
    assert not np.allclose(grid_features(x, X / 1000.0, None, K_TEST, IMAGE, FeatureSpec()), batch)


def test_spec_round_trip_and_bad_variant():
    spec = FeatureSpec(grid=Grid(12, 9), variant="D")
    assert FeatureSpec.from_dict(spec.to_dict()) == spec
    assert spec.size == 4 * 12 * 9
    with pytest.raises(InputError, match="variant"):
        FeatureSpec(variant="F")
    with pytest.raises(InputError, match="8x6"):
        Grid.parse("8 by 6")
    assert set(CHANNELS) == set(DEFAULT_SCALE)


def test_data_step_round_trips_and_is_appended_after_the_grid():
    spec = FeatureSpec(grid=Grid(4, 3), data_step=True, depth_mm=500.0)
    assert FeatureSpec.from_dict(spec.to_dict()) == spec
    assert "data_step" not in FeatureSpec().to_dict()  # a paper model's spec is as before
    assert spec.size == spec.grid_size + STEP_SIZE == 5 * 12 + STEP_SIZE
    with pytest.raises(JsonProblem, match="data_step must be true or false"):
        FeatureSpec.from_dict({**spec.to_dict(), "data_step": "yes"})
    rng = np.random.default_rng(4)
    x, X, *_ = random_frames(rng, frames=3, points=40, noise_px=0.5)
    mask = np.ones((3, 40), bool)
    mask[:, :6] = False
    with_step = grid_features(x, X, mask, K_TEST, IMAGE, spec)
    without = grid_features(x, X, mask, K_TEST, IMAGE, FeatureSpec(grid=Grid(4, 3), depth_mm=500.0))
    np.testing.assert_array_equal(with_step[:, : spec.grid_size], without)
    x2 = x.copy()
    x2[:, :6] = np.nan  # garbage on masked points
    for b in range(3):
        alone = grid_features(x2[b : b + 1], X[b : b + 1], mask[b : b + 1], K_TEST, IMAGE, spec)[0]
        np.testing.assert_allclose(alone, with_step[b], atol=1e-9)


def shifted_camera(dk):
    K = K_TEST.copy()
    K[[0, 1, 0, 1], [0, 1, 2, 2]] += dk
    return K


def test_data_step_reads_a_k_shift_from_a_3d_frame_and_knows_a_plane_does_not_fix_k():
    """The frame is imaged under K_c + dk: noise-free, the step says dk to the linearisation's
    2 %; with noise, within 3 of its own posterior sigmas, which are far below the prior's. On one
    plane f and c are not both fixed, and the step's sigmas say so."""
    dk = np.array([30.0, 30.0, -12.0, 8.0])  # px: OIS moves c by tens of px, AF breathes f
    spec = FeatureSpec(data_step=True)
    prior_px = STEP_PRIOR_REL * K_TEST[0, 0]
    for noise_px in (0.0, 0.3):
        x, X, *_ = random_frames(np.random.default_rng(5), frames=2, points=80, noise_px=noise_px, K=shifted_camera(dk))
        step = grid_features(x, X, None, K_TEST, IMAGE, spec)[:, spec.grid_size :]
        sigma_px = np.exp(step[:, 4:]) * prior_px
        error_px = np.abs(step[:, :4] / DEFAULT_SCALE["dx"] - dk)
        assert np.all(error_px <= 3 * sigma_px * (noise_px > 0) + 0.02 * np.abs(dk).max())
        assert sigma_px.max() < 0.05 * prior_px
    xp, Xp, *_ = random_frames(
        np.random.default_rng(6), frames=2, points=80, noise_px=0.3, K=shifted_camera(dk), planar=True
    )
    planar = grid_features(xp, Xp, None, K_TEST, IMAGE, spec)[:, spec.grid_size :]
    assert np.all(planar[:, 4:].max(1) > step[:, 4:].max() + 2.0)  # some parameter is left to the prior


def reference_moments(p2, p3, mask, K_c, rvec, tvec):
    """The moments written from their definition, point by point: the mean over the inference points
    of every product of two of [1, a, b, ab, a^2, b^2, z, a z, b z, s dx, s dy], the upper triangle in
    row order less [1 * 1] and [1 * z]."""
    R = g.rvec_to_matrix(rvec)
    cam = [R @ X + tvec for X, m in zip(p3, mask) if m]
    pmd = [(K_c @ (Xc / Xc[2]))[:2] - x for Xc, x, m in zip([R @ X + tvec for X in p3], p2, mask) if m]
    mean_inv_z = np.mean([1 / Xc[2] for Xc in cam])
    s = DEFAULT_SCALE["dx"]
    total = np.zeros((11, 11))
    for Xc, d in zip(cam, pmd):
        a, b, z = Xc[0] / Xc[2], Xc[1] / Xc[2], 1 / Xc[2] / mean_inv_z
        q = np.array([1, a, b, a * b, a * a, b * b, z, a * z, b * z, s * d[0], s * d[1]])
        total += np.outer(q, q)
    mean = total / len(cam)
    return [mean[i, j] for i in range(11) for j in range(i, 11) if (i, j) not in ((0, 0), (0, 6))]


def test_moments_equal_their_definition_and_ignore_the_world_unit_and_the_point_order():
    spec = FeatureSpec(grid=Grid(1, 1), variant="B", data_step=True, moments=True, depth_mm=500.0)
    assert FeatureSpec.from_dict(spec.to_dict()) == spec
    assert "moments" not in FeatureSpec(data_step=True).to_dict()  # a model without them reads as before
    assert spec.size == 2 + STEP_SIZE + MOMENT_SIZE and MOMENT_SIZE == 64
    with pytest.raises(JsonProblem, match="moments must be true or false"):
        FeatureSpec.from_dict({**spec.to_dict(), "moments": 1})
    rng = np.random.default_rng(7)
    x, X, K, rvec, tvec = random_frames(rng, frames=3, points=50, noise_px=1.5)
    mask = rng.random((3, 50)) > 0.3
    feats = grid_features(x, X, mask, K_TEST, IMAGE, spec, poses=(rvec, tvec))
    for b in range(3):
        want = reference_moments(x[b], X[b], mask[b], K_TEST, rvec[b], tvec[b])
        np.testing.assert_allclose(feats[b, -MOMENT_SIZE:], want, rtol=1e-9, atol=1e-12)
    # The step is as without the moments, and metres give the millimetres' moments.
    step_only = FeatureSpec(grid=Grid(1, 1), variant="B", data_step=True, depth_mm=500.0)
    np.testing.assert_array_equal(
        feats[:, :-MOMENT_SIZE], grid_features(x, X, mask, K_TEST, IMAGE, step_only, poses=(rvec, tvec))
    )
    np.testing.assert_allclose(
        grid_features(x, X / 1000.0, mask, K_TEST, IMAGE, spec, poses=(rvec, tvec / 1000.0)),
        feats,
        rtol=1e-7,
        atol=1e-9,
    )
    unmasked = grid_features(x, X, None, K_TEST, IMAGE, spec, poses=(rvec, tvec))
    for b in range(3):  # the rectifier's one frame equals the batch
        alone = grid_features(
            x[b : b + 1], X[b : b + 1], None, K_TEST, IMAGE, spec, poses=(rvec[b : b + 1], tvec[b : b + 1])
        )
        np.testing.assert_allclose(alone[0], unmasked[b], rtol=1e-12, atol=1e-15)
    order = rng.permutation(50)
    shuffled = grid_features(x[:, order], X[:, order], mask[:, order], K_TEST, IMAGE, spec, poses=(rvec, tvec))
    np.testing.assert_allclose(shuffled, feats, rtol=1e-9, atol=1e-12)


def test_too_few_inference_points_is_named():
    rng = np.random.default_rng(3)
    x, X, *_ = random_frames(rng, frames=1, points=10)
    mask = np.zeros((1, 10), bool)
    mask[0, :3] = True
    with pytest.raises(InputError, match="3 inference points"):
        grid_features(x, X, mask, K_TEST, IMAGE, FeatureSpec())
