import json

import numpy as np
import pytest
from helpers import point_thickness

from dimenet.runtime.errors import InputError
from dimenet.runtime.evaluation.conditions import (
    add_noise,
    drop_inference_points,
    empty_cells,
    occupancy,
    one_plane,
    two_objects,
)
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.rectify.grid import Grid

GRID_8X6 = Grid.parse("8x6")


def tiny_dataset():
    """Two frames on a 400x300 px image; a 4x3 grid has 100 px square cells (index = row*4 + col).

    Frame 0 infers from cells 0 and 5, frame 1 from cell 11; the valid-only points sit in other
    cells and must not count as occupied.
    """
    p2 = np.full((2, 8, 2), np.nan)
    p2[0, :6] = [(10, 10), (50, 60), (150, 150), (120, 180), (350, 50), (250, 250)]  # cells 0 0 5 5 3 10
    p2[1, :7] = [(390, 290), (310, 210), (10, 10), (150, 50), (250, 50), (50, 150), (150, 150)]  # 11 11 0 1 2 4 5
    valid = ~np.isnan(p2[..., 0])
    infer = np.zeros_like(valid)
    infer[0, :4] = True
    infer[1, :2] = True
    rng = np.random.default_rng(0)
    p3 = np.where(valid[..., None], rng.uniform(-100, 100, (2, 8, 3)) + [0, 0, 600], np.nan)
    return Dataset(
        image_size=np.array([400, 300], np.int64),
        points_2d=p2,
        points_3d=p3,
        valid=valid,
        infer_mask=infer,
        split=np.array(["test", "test"]),
        scene=np.array(["rig", "rig"]),
        meta=json.loads('{"device": "tiny"}'),
    )


def test_occupancy_hand_computed():
    grid = Grid.parse("4x3")
    assert occupancy(tiny_dataset(), grid) == pytest.approx((2 / 12 + 1 / 12) / 2)


def test_empty_cells_on_the_tiny_dataset():
    grid = Grid.parse("4x3")
    ds = tiny_dataset()
    out = empty_cells(ds, 0.5, grid, np.random.default_rng(1))
    # Frame 0: round(0.5 * 2) = 1 of its 2 cells emptied, whole cells at a time; frame 1 keeps its
    # only cell (at least one occupied cell always remains).
    kept = out.infer_mask[0, :4]
    assert kept.sum() == 2 and (kept[:2].all() != kept[2:].all())
    np.testing.assert_array_equal(out.infer_mask[1], ds.infer_mask[1])
    np.testing.assert_array_equal(out.valid, ds.valid)
    assert occupancy(out, grid) == pytest.approx((1 / 12 + 1 / 12) / 2)


@pytest.mark.parametrize("eta", [0.0, 0.2, 0.4, 0.6, 0.8])
def test_empty_cells_removes_round_eta_of_the_occupied_cells(s8_dataset, eta):
    out = empty_cells(s8_dataset, eta, GRID_8X6, np.random.default_rng(2))
    cells = GRID_8X6.cell_index(s8_dataset.points_2d, s8_dataset.image_size)
    for f in range(s8_dataset.n_frames):
        before = np.unique(cells[f][s8_dataset.infer_mask[f]])
        after = np.unique(cells[f][out.infer_mask[f]])
        m_p = len(before)
        assert len(after) == m_p - min(int(np.floor(eta * m_p + 0.5)), m_p - 1)
        # Emptied cells lose all their points, kept cells keep all theirs.
        in_kept = np.isin(cells[f], after) & s8_dataset.infer_mask[f]
        np.testing.assert_array_equal(out.infer_mask[f], in_kept)
    np.testing.assert_array_equal(out.valid, s8_dataset.valid)
    np.testing.assert_array_equal(out.points_2d, s8_dataset.points_2d)
    gamma0 = occupancy(s8_dataset, GRID_8X6)
    assert occupancy(out, GRID_8X6) == pytest.approx(gamma0 * (1 - eta), abs=0.03)


@pytest.mark.parametrize("n", [6, 64, 128, 256, 320])
def test_drop_keeps_exactly_n_inference_points_and_all_valid_points(s8_dataset, n):
    out = drop_inference_points(s8_dataset, n, np.random.default_rng(3))
    before = s8_dataset.infer_mask.sum(1)
    np.testing.assert_array_equal(out.infer_mask.sum(1), np.minimum(before, n))
    assert not np.any(out.infer_mask & ~s8_dataset.infer_mask)
    np.testing.assert_array_equal(out.valid, s8_dataset.valid)
    np.testing.assert_array_equal(out.points_3d, s8_dataset.points_3d)


def test_drop_samples_uniformly_and_reproducibly(s8_dataset):
    a = drop_inference_points(s8_dataset, 64, np.random.default_rng(5))
    b = drop_inference_points(s8_dataset, 64, np.random.default_rng(5))
    np.testing.assert_array_equal(a.infer_mask, b.infer_mask)
    # Over many frames every position of a 4-board frame is kept about 64/320 of the time.
    full = s8_dataset.infer_mask.sum(1) == 320
    rate = a.infer_mask[full].mean(0)
    assert rate.mean() == pytest.approx(64 / 320, rel=1e-9)
    assert np.abs(rate - 0.2).max() < 0.15


def test_noise_has_the_requested_std_and_spares_invalid_points(s8_dataset):
    out = add_noise(s8_dataset, 3.0, 0.1, np.random.default_rng(4))
    v = s8_dataset.valid
    d2 = (out.points_2d - s8_dataset.points_2d)[v]
    d3 = (out.points_3d - s8_dataset.points_3d)[v]
    assert d2.std() == pytest.approx(3.0, rel=0.02) and abs(d2.mean()) < 0.02
    assert d3.std() == pytest.approx(0.1, rel=0.02) and abs(d3.mean()) < 0.001
    np.testing.assert_array_equal(out.points_2d[~v], s8_dataset.points_2d[~v])  # NaN stays NaN
    np.testing.assert_array_equal(out.valid, v)
    np.testing.assert_array_equal(out.infer_mask, s8_dataset.infer_mask)
    same = add_noise(s8_dataset, 0.0, 0.0, np.random.default_rng(4))
    np.testing.assert_array_equal(same.points_2d, s8_dataset.points_2d)


def test_conditions_do_not_modify_their_input():
    ds = tiny_dataset()
    p2, infer = ds.points_2d.copy(), ds.infer_mask.copy()
    rng = np.random.default_rng(0)
    add_noise(ds, 1.0, 1.0, rng)
    drop_inference_points(ds, 6, rng)
    empty_cells(ds, 0.5, Grid.parse("4x3"), rng)
    two_objects(ds, rng)
    np.testing.assert_array_equal(ds.points_2d, p2)
    np.testing.assert_array_equal(ds.infer_mask, infer)


@pytest.mark.parametrize(
    "call",
    [
        lambda ds, rng: drop_inference_points(ds, 5, rng),
        lambda ds, rng: drop_inference_points(ds, 6.5, rng),
        lambda ds, rng: drop_inference_points(ds, True, rng),
        lambda ds, rng: drop_inference_points(ds, 64, 0),
        lambda ds, rng: add_noise(ds, -1.0, 0.0, rng),
        lambda ds, rng: add_noise(ds, 0.0, float("nan"), rng),
        lambda ds, rng: add_noise(ds, float("inf"), 0.0, rng),
        lambda ds, rng: add_noise(ds, "3", 0.0, rng),
        lambda ds, rng: empty_cells(ds, 1.0, GRID_8X6, rng),
        lambda ds, rng: empty_cells(ds, -0.1, GRID_8X6, rng),
        lambda ds, rng: empty_cells(ds, float("nan"), GRID_8X6, rng),
        lambda ds, rng: empty_cells(ds, 0.5, "8x6", rng),
        lambda ds, rng: occupancy(ds, "8x6"),
        lambda ds, rng: two_objects(ds, 0),
        lambda ds, rng: two_objects(ds, rng, group_points=(5, 10)),
        lambda ds, rng: two_objects(ds, rng, n_points=(40, 20)),
    ],
)
def test_bad_arguments_raise_input_error(call):
    with pytest.raises(InputError):
        call(tiny_dataset(), np.random.default_rng(0))


def test_per_frame_values(s8_dataset):
    F = s8_dataset.n_frames
    n = np.where(np.arange(F) % 2 == 0, 64, 128)
    dropped = drop_inference_points(s8_dataset, n, np.random.default_rng(6))
    np.testing.assert_array_equal(dropped.infer_mask.sum(1), np.minimum(s8_dataset.infer_mask.sum(1), n))
    sigma = np.where(np.arange(F) < F // 2, 0.0, 2.0)
    noisy = add_noise(s8_dataset, sigma, 0.0, np.random.default_rng(7))
    d2 = noisy.points_2d - s8_dataset.points_2d
    assert np.nanstd(d2[: F // 2]) == 0.0 and np.nanstd(d2[F // 2 :]) == pytest.approx(2.0, rel=0.03)
    eta = np.where(np.arange(F) % 2 == 0, 0.0, 0.5)
    emptied = empty_cells(s8_dataset, eta, GRID_8X6, np.random.default_rng(8))
    np.testing.assert_array_equal(emptied.infer_mask[::2], s8_dataset.infer_mask[::2])
    assert emptied.infer_mask[1::2].sum() < s8_dataset.infer_mask[1::2].sum()
    with pytest.raises(InputError):
        drop_inference_points(s8_dataset, np.full(F + 1, 64), np.random.default_rng(0))


def _uncovered_by_every_pair(points: np.ndarray, kept: np.ndarray, group: int) -> bool:
    """True when no two of ``points`` (n, 2) have ``kept`` (k, 2) all among their ``group``
    nearest points (ties broken as a stable sort does)."""
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    rank = np.argsort(np.argsort(d, axis=1, kind="stable"), axis=1, kind="stable")  # rank[c, i]
    where = [int(np.flatnonzero((points == x).all(1))[0]) for x in kept]
    outside = (rank[:, where] >= group).astype(int)  # (n, k): kept point not in c's group
    return not np.any(outside @ outside.T == 0)


def test_two_objects_keeps_a_subset_of_two_groups_around_far_apart_centres(s8_dataset):
    rig = s8_dataset.select(s8_dataset.scene == "rig")
    out = two_objects(rig, np.random.default_rng(0))
    np.testing.assert_array_equal(out.valid, rig.valid)
    np.testing.assert_array_equal(out.points_2d, rig.points_2d)  # label noise is add_noise's
    n = out.infer_mask.sum(1)
    assert np.all(out.infer_mask <= rig.infer_mask) and np.all((40 <= n) & (n <= 100))
    for f in range(0, rig.n_frames, 23):
        x = rig.points_2d[f][rig.infer_mask[f]]
        assert not _uncovered_by_every_pair(x, rig.points_2d[f][out.infer_mask[f]], 140)
    # One group of 6 around each centre: the second centre is drawn by distance from the first,
    # so the groups lie further apart (1.22x here) than around two uniformly drawn centres (1.0x).
    pairs = two_objects(rig, np.random.default_rng(1), group_points=(6, 6), n_points=(12, 12))
    rng = np.random.default_rng(2)
    extent = lambda x: np.linalg.norm(x[:, None] - x[None], axis=-1).max()  # noqa: E731
    apart, uniform = [], []
    for f in range(rig.n_frames):
        x = rig.points_2d[f][pairs.infer_mask[f]]
        assert 6 <= len(x) <= 12  # fewer where the groups overlap
        apart.append(extent(x))
        points = rig.points_2d[f][rig.infer_mask[f]]
        for _ in range(10):
            near = [
                np.argsort(np.linalg.norm(points - points[c], axis=1))[:6] for c in rng.integers(len(points), size=2)
            ]
            uniform.append(extent(points[np.union1d(*near)]))
    assert np.mean(apart) > 1.12 * np.mean(uniform)
    again = two_objects(rig, np.random.default_rng(0))
    np.testing.assert_array_equal(again.infer_mask, out.infer_mask)


def test_two_objects_keeps_frames_with_too_few_points():
    ds = tiny_dataset()
    one = ds.infer_mask.copy()
    one[1] = False
    one[1, 0] = True
    out = two_objects(
        Dataset(**{**ds.__dict__, "infer_mask": one}), np.random.default_rng(0), group_points=(6, 6), n_points=(6, 6)
    )
    np.testing.assert_array_equal(out.infer_mask[1], one[1])  # one point: unchanged
    np.testing.assert_array_equal(out.infer_mask[0], ds.infer_mask[0])  # 4 points, all in both groups


def test_one_plane_keeps_the_inference_points_of_one_board(s8_dataset):
    frames = s8_dataset.select(np.flatnonzero(s8_dataset.scene == "rig")[:6])
    planes = one_plane(frames, np.random.default_rng(0))
    for f in range(frames.n_frames):
        kept = planes.infer_mask[f]
        assert np.all(frames.infer_mask[f] >= kept) and 4 <= kept.sum() < frames.infer_mask[f].sum()
        assert point_thickness(np.ascontiguousarray(frames.points_3d[f][kept])) < 1e-9
        assert point_thickness(np.ascontiguousarray(frames.points_3d[f][frames.infer_mask[f]])) > 1e-3
