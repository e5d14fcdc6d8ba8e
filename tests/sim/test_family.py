"""The randomised camera family: deterministic, in range, away from the paper's cameras, and every
camera simulates valid datasets; `dimenet simulate --family N` writes one file per camera."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.sim import family
from dimenet.runtime.sim.family import (
    SIZES_PX,
    camera_seed,
    family_profile,
    family_profiles,
    family_sizes,
    hfov_deg,
    near_paper_profile,
    simulate_family,
)
from dimenet.runtime.sim.profiles import PROFILES
from dimenet.runtime.sim.simulator import simulate

SEEDS = (0, 1, 2, 3, 4)


def test_same_seed_same_family_other_seed_other_family():
    assert family_profiles(20, 7) == family_profiles(20, 7)
    assert family_profiles(20, 7) != family_profiles(20, 8)
    assert family_profiles(20, 7)[:5] == family_profiles(5, 7)  # camera i does not depend on n
    rng = lambda: np.random.default_rng(3)  # noqa: E731
    assert family_profile(rng(), "cam") == family_profile(rng(), "cam")


def test_sizes_cycle_so_every_large_enough_family_holds_the_stream_sizes():
    assert len(set(SIZES_PX)) == len(SIZES_PX) >= 13
    assert {(1920, 1080), (1280, 720)} <= set(SIZES_PX)
    for seed in SEEDS:
        sizes = family_sizes(2 * len(SIZES_PX), seed)
        assert sorted(sizes[: len(SIZES_PX)]) == sorted(SIZES_PX) == sorted(sizes[len(SIZES_PX) :])
        assert [p.image_size_px for p in family_profiles(len(SIZES_PX), seed, frames=(1, 0))] == sizes[:13]
    assert family_sizes(13, 0) != family_sizes(13, 1)  # a seeded order, not a fixed one
    for width, height in SIZES_PX:
        assert 1280 <= width <= 8000 and width * 3 in (height * 4, height * 16 // 3)


def test_camera_parameters_stay_in_their_ranges():
    cameras = [p for seed in SEEDS for p in family_profiles(40, seed)]
    for p in cameras:
        w, h = p.image_size_px
        scale = np.tan(np.radians(family.REFERENCE_HFOV_DEG / 2)) / np.tan(np.radians(hfov_deg(p) / 2))
        assert 55.0 <= hfov_deg(p) <= 85.0
        assert 2.5 <= p.focal_length_mm <= 7.0
        assert p.focal_px == pytest.approx(w / 2 / np.tan(np.radians(hfov_deg(p) / 2)))
        assert abs(p.pixel_aspect - 1.0) <= 0.01
        assert np.all(np.abs(p.centre_offset_px) <= 0.02 * w)
        assert 0.1 <= p.corner_sigma_px <= 0.6
        assert 0.4 <= p.shake_sigma_deg <= 1.6 and 0.7 <= p.ois_stroke_deg <= 1.8
        assert p.ois_stroke_deg >= p.shake_sigma_deg
        assert p.label_sigma_px == pytest.approx(4.9 * w / 4032) and p.border_margin_px == max(
            2.0, 4.0 * w / 4032, 5 * p.corner_sigma_px
        )
        assert p.distance_mm == pytest.approx((400.0 * scale, 700.0 * scale))
        assert p.aim_jitter_mm == pytest.approx(50 * scale)
        assert (p.n_train, p.n_test) == (80, 20) and p.af_error_rel == 0.03
        assert (p.view_max_deg, p.roll_max_deg) == (25.0, 10.0)
    hfov = [hfov_deg(p) for p in cameras]
    assert min(hfov) < 57 and max(hfov) > 83  # the whole range is used
    assert len({p.name for p in cameras}) == len(cameras) and cameras[3].name == "family-s0-003"


def test_paper_profiles_are_near_and_no_family_camera_is():
    assert all(near_paper_profile(p) for p in PROFILES.values())
    cameras = [p for seed in range(8) for p in family_profiles(52, seed, frames=(1, 0))]
    assert not any(near_paper_profile(p) for p in cameras)
    # 4000x3000 is the one listed size near 4032x3024: its cameras keep away from the paper's fields of view
    hfov = [hfov_deg(p) for p in cameras if p.image_size_px == (4000, 3000)]
    assert len(hfov) >= 16 and all(abs(v - hfov_deg(q)) > 4.0 for v in hfov for q in PROFILES.values())
    s8 = PROFILES["galaxy-s8"]
    assert hfov_deg(s8) == pytest.approx(67.2, abs=0.05)
    near = family_profile(np.random.default_rng(0), "x", (4032, 3024))
    assert not near_paper_profile(near) and abs(hfov_deg(near) - 67.2) > 4.0


def test_the_exclusion_rule_is_size_aspect_and_field_of_view():
    s8 = PROFILES["galaxy-s8"]
    f_mm = s8.focal_length_mm
    with_size = lambda w, h, hfov=67.2: family.DeviceProfile(  # noqa: E731
        **{**asdict(s8), "image_size_px": (w, h), "pixel_pitch_um": f_mm * 1e3 / (w / 2 / np.tan(np.radians(hfov / 2)))}
    )
    assert near_paper_profile(with_size(3700, 2775)) and near_paper_profile(with_size(4400, 3300))
    assert not near_paper_profile(with_size(3600, 2700))  # 10.7 % narrower
    assert not near_paper_profile(with_size(4032, 2268))  # 16:9
    assert near_paper_profile(with_size(4032, 3024, 71.5)) and not near_paper_profile(with_size(4032, 3024, 72.5))


def test_bad_family_arguments_raise_input_error():
    for n, seed in ((0, 0), (1001, 0), (1.5, 0), (True, 0), (3, -1)):
        with pytest.raises(InputError):
            family_profiles(n, seed)
    for frames in ((0, 0), (-1, 3), (1,), (1.0, 2)):
        with pytest.raises(InputError, match="frames"):
            family_profiles(2, 0, frames=frames)


def check_dataset(ds, profile, natural, planar):
    """A family camera's dataset: its counts, image, moving K and points inside the image."""
    w, h = profile.image_size_px
    assert tuple(ds.image_size) == (w, h) and ds.meta["device"]["name"] == profile.name
    assert ds.meta["device"] == asdict(profile)
    rig = ds.scene == "rig"
    assert (ds.frames_in("train") & rig).sum() == profile.n_train
    assert (ds.frames_in("test") & rig).sum() == profile.n_test
    assert (ds.scene == "natural").sum() == natural and (ds.scene == "planar").sum() == planar
    assert np.all(ds.valid[rig | (ds.scene == "planar")].sum(1) >= 160)  # >= 2 whole boards
    seen = ds.points_2d[ds.valid & (ds.scene != "natural")[:, None]]
    assert np.all((seen >= 0) & (seen <= [w - 1, h - 1]))
    fx, fy, cx, cy = k_params(ds.K_true).T
    assert np.ptp(cx) > 0 and np.ptp(cy) > 0 and np.ptp(fx) > 0  # OIS and focus breathing move K per frame
    np.testing.assert_allclose(fy, fx * profile.pixel_aspect)
    limit = fx * np.tan(np.radians(profile.ois_stroke_deg))
    assert np.all(np.abs(np.c_[cx, cy] - profile.centre_px) <= limit[:, None] + 1e-9)


def test_every_family_camera_simulates_valid_datasets():
    cameras = family_profiles(30, 11, frames=(4, 2))
    assert {(1920, 1080), (1280, 720)} <= {p.image_size_px for p in cameras}
    for i, p in enumerate(cameras):
        check_dataset(simulate(p, seed=camera_seed(11, i), natural_frames=1, planar_frames=1), p, 1, 1)


@pytest.mark.parametrize("hfov", [55.0, 85.0])
@pytest.mark.parametrize("size", [(1280, 720), (7680, 4320), (8000, 6000), (1280, 960)])
def test_extreme_fields_of_view_and_sizes_find_usable_views(monkeypatch, hfov, size):
    monkeypatch.setattr(family, "HFOV_DEG", (hfov, hfov))
    p = family_profile(np.random.default_rng(int(hfov) + size[0]), "extreme", size, frames=(6, 0))
    assert hfov_deg(p) == pytest.approx(hfov)
    check_dataset(simulate(p, seed=1, natural_frames=2, planar_frames=1), p, 2, 1)


def test_simulate_family_yields_each_camera_with_its_dataset():
    out = list(simulate_family(3, 4, natural_frames=1, frames=(3, 1)))
    assert [p for p, _ in out] == family_profiles(3, 4, frames=(3, 1))
    for i, (_, ds) in enumerate(out):
        assert ds.meta["family"] == {"seed": 4, "index": i, "cameras": 3, "scenes": "paper"} and ds.meta[
            "seed"
        ] == camera_seed(4, i)
        assert ds.frame_id[0] == f"family-s4-{i:03d}-0000"
    assert len({camera_seed(4, i) for i in range(50)}) == 50


def test_cli_writes_one_dataset_per_camera(tmp_path, capsys):
    out = tmp_path / "family"
    assert main(["simulate", "--family", "2", "--seed", "3", "--planar-frames", "1", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    names = [p.name for p in family_profiles(2, 3)]
    assert names == ["family-s3-000", "family-s3-001"]
    assert sorted(f.name for f in out.iterdir()) == [f"{n}.npz" for n in names]
    assert len(lines) == 3 and lines[0].startswith(names[0]) and "80 train + 20 test rig frames" in lines[0]
    assert "2 cameras" in lines[2] and str(out) in lines[2]
    ds = read_dataset(out / "family-s3-001.npz")
    assert ds.n_frames == 80 + 20 + 1 and ds.meta["device"]["name"] == "family-s3-001"
    assert ds.meta["family"] == {"seed": 3, "index": 1, "cameras": 2, "scenes": "paper"}


def test_cli_help_ends_with_a_family_example(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out.rstrip()
    assert "--family" in text.split("example:")[1] and text.splitlines()[-1].strip().startswith("dimenet simulate")


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--profile", "galaxy-s8", "--family", "3"], "not allowed with"),
        ([], "one of the arguments --profile --family --recording is required"),
        (["--family", "0"], "--family"),
        (["--family", "1001"], "--family"),
        (["--family", "abc"], "--family"),
    ],
)
def test_cli_needs_exactly_one_of_profile_and_family(tmp_path, capsys, argv, words):
    assert main(["simulate", *argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "x").exists()
