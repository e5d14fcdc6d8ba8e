"""The scene family: random rigs (``sim.scenes.random_rig``), their framing, and ``simulate --family --scenes``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.rig import paper_rig, rig_to_dict
from dimenet.runtime.geometry import RIG_VIEW_RATIO, project, spans_3d
from dimenet.runtime.sim import scenes
from dimenet.runtime.sim.family import (
    OIS_OFF_SHARE,
    VIDEO_SHARE,
    VIDEO_STROKE_DEG,
    family_member,
    family_profiles,
    has_ois,
)
from dimenet.runtime.sim.scenes import build_errors_mm, extent_mm, framed, random_rig
from dimenet.runtime.sim.simulator import simulate


def rigs(n: int = 60) -> list:
    return [random_rig(np.random.default_rng(seed)) for seed in range(n)]


def test_random_rigs_stay_in_their_ranges_and_span_3d():
    drawn = rigs()
    counts = {len(r.boards) for r in drawn}
    assert counts == set(range(scenes.BOARDS[0], scenes.BOARDS[1] + 1))  # every count drawn in 60 rigs
    for rig in drawn:
        assert len({b.square_mm for b in rig.boards}) == 1
        assert scenes.SQUARE_MM[0] <= rig.boards[0].square_mm <= scenes.SQUARE_MM[1]
        for b in rig.boards:
            assert all(scenes.SQUARES[0] - 1 <= v <= scenes.SQUARES[1] - 1 for v in b.inner_corners)
            tilt = math.degrees(math.acos(np.clip(b.normal()[2], -1, 1)))  # off facing the camera (+z)
            assert tilt <= scenes.TILT_DEG[1] + 1e-9
        n0, n1 = rig.boards[0].normal(), rig.boards[1].normal()
        assert math.degrees(math.acos(np.clip(n0 @ n1, -1, 1))) >= scenes.MIN_PLANE_ANGLE_DEG - 1e-9
        assert spans_3d(rig.points(), RIG_VIEW_RATIO)


def test_boards_of_a_random_rig_do_not_overlap_as_the_camera_sees_them_face_on():
    """Each board sits in its own cell: seen from far along the view axis, no two boards' corner hulls meet."""
    for rig in rigs(30):
        boxes = [(b.points()[:, :2].min(0), b.points()[:, :2].max(0)) for b in rig.boards]
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                (lo_a, hi_a), (lo_b, hi_b) = boxes[i], boxes[j]
                assert np.any(hi_a < lo_b) or np.any(hi_b < lo_a), (i, j)


def test_same_generator_state_same_rig():
    a, b = random_rig(np.random.default_rng(5)), random_rig(np.random.default_rng(5))
    assert rig_to_dict(a) == rig_to_dict(b)
    assert rig_to_dict(a) != rig_to_dict(random_rig(np.random.default_rng(6)))


@pytest.mark.parametrize("fill", [scenes.FILL, (0.2, 1 / 3)])
def test_framing_puts_the_rig_between_a_fifth_of_the_image_and_most_of_it(fill):
    """The training's framing, and the far one a held-out family draws."""
    profile = family_profiles(1, 0)[0]
    rig = random_rig(np.random.default_rng(1))
    near, far = framed(profile, rig, fill).distance_mm
    width_px = profile.image_size_px[0]
    for distance, share in ((near, fill[1]), (far, fill[0])):
        # a segment of the rig's extent, centred and face on at that distance, spans `share` of the width
        ends = np.array([[-extent_mm(rig) / 2, 0, distance], [extent_mm(rig) / 2, 0, distance]])
        px = project(ends, profile.nominal_K, np.zeros(3), np.zeros(3))
        assert (px[1, 0] - px[0, 0]) / width_px == pytest.approx(share, rel=1e-9)


@pytest.mark.parametrize("fill", [(0.0, 0.5), (0.5, 0.4), (0.2, 1.5)])
def test_a_framing_outside_the_image_is_refused(fill):
    with pytest.raises(InputError, match="fill must be"):
        framed(family_profiles(1, 0)[0], random_rig(np.random.default_rng(1)), fill)


def test_a_random_scene_family_member_sees_its_own_rig_and_keeps_k_star_observable():
    profile = family_profiles(2, 3, frames=(12, 4))[1]
    ds = family_member(profile, 1, 3, 2, scenes="random")
    assert ds.meta["family"]["scenes"] == "random"
    assert ds.meta["rig"] != rig_to_dict(paper_rig())
    assert ds.meta["rig"] == rig_to_dict(random_rig(np.random.default_rng(np.random.SeedSequence(3, spawn_key=(3, 1)))))
    for k in range(ds.n_frames):
        seen = ds.valid[k]
        assert spans_3d(ds.points_3d[k][seen], RIG_VIEW_RATIO)
    again = family_member(profile, 1, 3, 2, scenes="random")
    assert np.array_equal(again.points_2d, ds.points_2d, equal_nan=True)


def test_paper_scenes_are_the_family_as_before():
    profile = family_profiles(1, 4, frames=(6, 2))[0]
    default = family_member(profile, 0, 4, 1)
    paper = family_member(profile, 0, 4, 1, scenes="paper")
    assert np.array_equal(default.points_2d, paper.points_2d, equal_nan=True)
    assert paper.meta["rig"] == rig_to_dict(paper_rig())


def test_unknown_scenes_raise_input_error():
    profile = family_profiles(1, 0, frames=(2, 1))[0]
    with pytest.raises(InputError, match="scenes must be one of paper, random"):
        family_member(profile, 0, 0, 1, scenes="rooms")


def test_cli_writes_random_scene_cameras_and_refuses_them_without_family(tmp_path, capsys):
    out = tmp_path / "fam"
    assert main(["simulate", "--family", "2", "--seed", "2", "--scenes", "random", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("a rig of") == 2
    written = [read_dataset(out / f"family-s2-00{i}.npz") for i in range(2)]
    assert written[0].meta["rig"] != written[1].meta["rig"]
    for line, ds in zip(printed.splitlines(), written):  # the camera as simulated: camera 0 has no OIS
        kind = "plain" if ds.meta["image_errors"]["charuco_missing"] is None else "ChArUco"
        assert f"stroke {ds.meta['device']['ois_stroke_deg']:.2f} deg" in line and f" {kind} boards" in line
    assert "stroke 0.00 deg" in printed
    assert main(["simulate", "--profile", "galaxy-s8", "--scenes", "random", "--out", str(tmp_path / "x.npz")]) == 2
    assert "--scenes random needs --family" in capsys.readouterr().err


def test_a_share_of_random_scene_cameras_has_no_ois_and_a_still_principal_point_and_a_share_films_video():
    """OIS_OFF_SHARE of the cameras (front cameras, OIS disabled): the principal point never moves, f still breathes;
    the others' does, and VIDEO_SHARE of those are video cameras with a larger stroke. Paper scenes keep every
    camera's OIS as drawn."""
    n = 40
    off = video = 0
    for i, profile in enumerate(family_profiles(n, 2, frames=(4, 2))):
        ds = family_member(profile, i, 2, n, scenes="random")
        c_spread_px = np.ptp(ds.K_true[:, :2, 2], axis=0)
        stroke_deg = ds.meta["device"]["ois_stroke_deg"]
        assert has_ois(2, i) == (stroke_deg > 0.0)
        if stroke_deg == 0.0:
            off += 1
            assert np.all(c_spread_px == 0.0) and np.ptp(ds.K_true[:, 0, 0]) > 0.0
        else:
            assert np.all(c_spread_px > 0.0)
            if stroke_deg != profile.ois_stroke_deg:
                video += 1
                assert VIDEO_STROKE_DEG[0] <= stroke_deg <= VIDEO_STROKE_DEG[1]
                assert ds.meta["device"]["shake_sigma_deg"] < stroke_deg
        assert (
            family_member(profile, i, 2, n, scenes="paper").meta["device"]["ois_stroke_deg"] == profile.ois_stroke_deg
        )
    assert 0.5 * OIS_OFF_SHARE * n <= off <= 1.75 * OIS_OFF_SHARE * n
    assert 1 <= video <= 2.5 * VIDEO_SHARE * (n - off)


def test_a_sagging_sheet_bends_along_its_normal_and_stays_flat_at_its_edges(monkeypatch):
    monkeypatch.setattr(scenes, "PLACEMENT_DEG", 0.0)
    monkeypatch.setattr(scenes, "PLACEMENT_MM", 0.0)
    rig = random_rig(np.random.default_rng(2))
    offsets = build_errors_mm(rig, np.random.default_rng(3))
    start = 0
    for board in rig.boards:
        off = offsets[start : start + board.n_points]
        start += board.n_points
        along_normal = off @ board.normal()
        assert np.allclose(off, along_normal[:, None] * board.normal(), atol=1e-12)  # a bend, no slide
        assert np.max(np.abs(along_normal)) <= scenes.SAG_MM
        grid = along_normal.reshape(board.inner_corners[1], board.inner_corners[0])
        flat_rows = np.allclose(grid[0], 0.0) and np.allclose(grid[-1], 0.0)
        flat_cols = np.allclose(grid[:, 0], 0.0) and np.allclose(grid[:, -1], 0.0)
        assert flat_rows or flat_cols, grid  # zero sag at the two edges across the bent axis


def test_the_camera_sees_the_built_rig_and_the_dataset_keeps_the_rigs_points():
    profile = family_profiles(1, 6, frames=(5, 2))[0]
    rig = random_rig(np.random.default_rng(4))
    framed_profile = framed(profile, rig)
    offsets = build_errors_mm(rig, np.random.default_rng(5))
    nominal = simulate(framed_profile, seed=9, rig=rig)
    built = simulate(framed_profile, seed=9, rig=rig, rig_offsets_mm=offsets)
    zero = simulate(framed_profile, seed=9, rig=rig, rig_offsets_mm=np.zeros_like(offsets))
    assert np.array_equal(zero.points_2d, nominal.points_2d, equal_nan=True)
    assert np.array_equal(built.valid, nominal.valid) and np.array_equal(built.K_true, nominal.K_true)
    assert np.array_equal(built.points_3d, nominal.points_3d, equal_nan=True)  # the file's points, not the built ones
    moved = np.linalg.norm(built.points_2d - nominal.points_2d, axis=-1)[built.valid]
    assert 0.0 < np.median(moved) and np.max(moved) < 20.0  # a few mm at the rig's distance: pixels, not frames
    with pytest.raises(InputError, match="rig_offsets_mm"):
        simulate(framed_profile, seed=9, rig=rig, rig_offsets_mm=offsets[:-1])
