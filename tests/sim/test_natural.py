"""Random natural scenes (``sim.natural.random_natural``) and the natural frames of a random-scene family."""

from __future__ import annotations

import numpy as np

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.rig import paper_rig
from dimenet.runtime.sim.family import family_member, family_profiles
from dimenet.runtime.sim.natural import LABEL_NOISE_PX, MODEL_ERROR, NATURAL_KINDS, NATURAL_POINTS, random_natural


def test_random_natural_scenes_stay_in_their_ranges_around_a_board_facing_the_camera():
    board = paper_rig().boards[0]
    kinds = set()
    for seed in range(40):
        natural = random_natural(board, 800.0, np.random.default_rng(seed))
        scene, features = natural.scene, natural.scene.group < 0
        kinds.add(natural.kind)
        assert NATURAL_POINTS[0] - 1 <= features.sum() <= NATURAL_POINTS[1]  # a feature under the board is dropped
        assert LABEL_NOISE_PX[0] <= natural.label_sigma_px <= LABEL_NOISE_PX[1]
        assert MODEL_ERROR[0] * 800.0 <= natural.model_sigma_mm <= MODEL_ERROR[1] * 800.0
        assert natural.min_seen <= features.sum()
        on_board = scene.points[scene.group == 0]
        assert np.ptp(on_board[:, 2]) == 0.0 and np.all(scene.normals[scene.group == 0] == (0.0, 0.0, -1.0))
        assert np.all(np.abs(on_board[:, :2].mean(0)) < 1e-9)  # centred in front of the scene
        assert np.all(np.abs(scene.points[features]) <= 800.0)
        # every feature faces a camera in front of the scene (no back or bottom faces are labelled)
        assert np.all((scene.normals[features] @ (0.0, 0.0, -1.0) >= 0) & (scene.normals[features][:, 1] <= 0))
    assert kinds == set(NATURAL_KINDS)
    a, b = (random_natural(board, 800.0, np.random.default_rng(7)) for _ in range(2))
    np.testing.assert_array_equal(a.scene.points, b.scene.points)


def test_a_random_scene_family_s_natural_frames_see_its_board_and_label_only_the_features():
    profile = family_profiles(2, 9, frames=(6, 2))[1]
    ds = family_member(profile, 1, 9, 2, natural_frames=4, scenes="random")
    natural = ds.scene == "natural"
    assert natural.sum() == 4 and np.all(ds.split[natural] == "test")
    meta = ds.meta["natural_scene"]
    assert meta["kind"] in NATURAL_KINDS and LABEL_NOISE_PX[0] <= meta["label_sigma_px"] <= LABEL_NOISE_PX[1]
    for k in np.flatnonzero(natural):
        infer, valid = ds.infer_mask[k], ds.valid[k]
        assert infer.sum() >= 12 and np.all(valid[infer]) and (valid & ~infer).sum() > 0  # the board: valid only
    # the rig frames are those of the family without natural frames, array for array
    plain = family_member(profile, 1, 9, 2, scenes="random")
    rig = ds.scene == "rig"
    P = plain.points_2d.shape[1]
    np.testing.assert_array_equal(ds.points_2d[rig][:, :P], plain.points_2d)
    np.testing.assert_array_equal(ds.K_true[rig], plain.K_true)


def test_simulate_writes_a_random_scene_family_with_natural_frames(tmp_path, capsys):
    out = tmp_path / "nat"
    args = ["simulate", "--family", "2", "--seed", "5", "--scenes", "random", "--natural-frames", "2"]
    assert main([*args, "--out", str(out)]) == 0
    assert capsys.readouterr().out.count("2 natural") == 2
    features = [read_dataset(out / f"family-s5-00{i}.npz").meta["natural_scene"]["features"] for i in range(2)]
    assert all(n >= NATURAL_POINTS[0] - 1 for n in features)
