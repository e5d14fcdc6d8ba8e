"""`dimenet evaluate --suite real`: the real photo sets (../shared/real-photos) ingested, calibrated with
and without a lens and rectified in both modes by each bundled model meet the do-no-harm targets; without
the sets the suite says it skipped them, and --photos naming a folder without them is an error."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dimenet.runtime.bench.real_suite import SETS, missing_sets
from dimenet.runtime.cli.main import main

ROOT = Path(__file__).resolve().parents[2].parent / "shared" / "real-photos"


@pytest.mark.skipif(bool(missing_sets(ROOT)), reason=f"the real photos are not all there: {ROOT}")
@pytest.mark.parametrize("model", ["default", "paper-rig"])
def test_the_real_photo_suite_meets_its_targets(capsys, model):
    assert main(["evaluate", "--suite", "real", "--photos", str(ROOT), "--model", model, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    rows = report["rows"]
    assert report["missing"] == [] and len(rows) == len(SETS) * 2 * 2  # sets x lens x mode
    for row in rows:
        assert row["problem"] is None and row["met"] and row["worse"] == 0, row
    huawei = [r for r in rows if r["set_name"] == "huawei-y5"]
    assert all(r["covered"] >= 0.9 and r["median_dc_px"] <= 5.0 for r in huawei)


def test_without_the_sets_the_suite_says_it_skipped_them(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", "--suite", "real"]) == 0
    assert "skipped" in capsys.readouterr().out
    assert main(["evaluate", "--suite", "real", "--photos", str(tmp_path)]) == 2
    assert "none of the suite's sets" in capsys.readouterr().err


def _suite_folder(tmp_path: Path, photos: dict) -> Path:
    """A suite root holding the ortho-left set: the paper rig's file as its rig and ``photos`` (name -> bytes)."""
    from dimenet.runtime.assets import asset

    folder = tmp_path / "photos" / "ortho"
    folder.mkdir(parents=True)
    (folder / "rig.json").write_bytes(asset("paper_rig.json").read_bytes())
    for name, blob in photos.items():
        (folder / name).write_bytes(blob)
    return folder.parent


def test_each_photo_the_suite_drops_is_named_with_why(tmp_path, capsys):
    # issue 48: an undecodable photo was dropped without a word, and a set of only such photos was a traceback
    root = _suite_folder(tmp_path, {"left.jpg": b"", "left_calib.jpg": b"not a jpeg"})
    assert main(["evaluate", "--suite", "real", "--photos", str(root)]) == 1
    out, err = capsys.readouterr()
    dropped = [line for line in err.splitlines() if "dropped" in line]
    assert len(dropped) == 2
    for line, name in zip(dropped, ("left.jpg", "left_calib.jpg")):
        assert line.startswith(f"real-photo suite: ortho-left: dropped {root / 'ortho' / name}: "), line
    assert "error: none of the 2 photos of ortho-left gave a frame" in out


@pytest.mark.skipif(not (ROOT / "ortho" / "left.jpg").is_file(), reason=f"the real photos are not there: {ROOT}")
def test_a_dropped_photo_beside_a_good_one_is_named(tmp_path, capsys):
    root = _suite_folder(tmp_path, {"left.jpg": (ROOT / "ortho" / "left.jpg").read_bytes(), "left_calib.jpg": b"x"})
    (root / "ortho" / "rig.json").write_bytes((ROOT / "ortho" / "rig.json").read_bytes())
    assert main(["evaluate", "--suite", "real", "--photos", str(root), "--json"]) in (0, 1)
    out, err = capsys.readouterr()
    dropped = [line for line in err.splitlines() if "dropped" in line]
    assert len(dropped) == 1 and "unsupported image format" in dropped[0]
    assert dropped[0].startswith(f"real-photo suite: ortho-left: dropped {root / 'ortho' / 'left_calib.jpg'}: ")
    assert json.loads(out)["rows"][0]["frames"] == 1  # the set still ran on its good photo
