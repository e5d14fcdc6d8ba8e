"""`dimenet samples --out DIR`: the inputs the README's and the help's examples read, which no other command
makes (rec.csv, cam.json, frames.npz, the real-photo sets' rig files), written from the bundled files and
usable as the examples use them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dimenet.runtime.assets import asset
from dimenet.runtime.bench.real_suite import RIG_ASSETS, SETS
from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.camera_file import read_camera
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.points import read_points
from dimenet.runtime.formats.rig import load_rig

SHARED = Path(__file__).resolve().parents[3] / "shared" / "real-photos"


def test_samples_writes_what_the_examples_read(tmp_path, capsys):
    assert main(["samples", "--out", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 5 and all(": " in line for line in lines)
    assert (tmp_path / "frames.npz").read_bytes() == asset("example_frames.npz").read_bytes()
    frames = read_dataset(tmp_path / "frames.npz")
    camera = read_camera(tmp_path / "cam.json")
    assert camera.image_size == tuple(int(v) for v in frames.image_size)
    recorded = list(read_points(tmp_path / "rec.csv"))
    assert len(recorded) == frames.n_frames == 8
    for k, frame in enumerate(recorded):
        valid = frames.valid[k]
        np.testing.assert_allclose(frame.points_2d, frames.points_2d[k][valid], atol=5e-5)
        np.testing.assert_allclose(frame.points_3d, frames.points_3d[k][valid], atol=5e-5)
    out = tmp_path / "rec.jsonl"
    assert (
        main(
            [
                "rectify",
                "--points",
                str(tmp_path / "rec.csv"),
                "--camera",
                str(tmp_path / "cam.json"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 9 and all("K" in r for r in records[1:])


def test_the_real_photo_rigs_are_the_sets_and_load(tmp_path):
    assert main(["samples", "--out", str(tmp_path)]) == 0
    assert set(RIG_ASSETS) == {s.folder for s in SETS}
    for folder in RIG_ASSETS:
        written = tmp_path / "real-photos" / folder / "rig.json"
        assert load_rig(written).boards
        if not (SHARED / folder / "rig.json").is_file():
            pytest.skip(f"{SHARED} is not here")
        assert json.loads(written.read_text()) == json.loads((SHARED / folder / "rig.json").read_text())
