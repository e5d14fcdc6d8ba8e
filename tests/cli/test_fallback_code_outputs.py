"""`dimenet rectify`'s outputs carry each frame's fallback_code beside its fallback: RESULT.npz
and --json, read back equal to what the rectifier returns."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
from helpers import example_camera

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.rectify.rectifier import Rectifier


def test_a_fallen_back_frame_s_code_round_trips_through_the_npz_and_the_json(frames, tmp_path, capsys):
    natural = frames.select(frames.scene == "natural")
    noisy = natural.points_2d.copy()
    noise = np.random.default_rng(1).normal(0, 60.0, noisy[0].shape)
    noisy[0] = np.clip(noisy[0] + noise, 0, natural.image_size - 1.0)  # far beyond the model's range
    data = tmp_path / "noisy.npz"
    write_dataset(replace(natural, points_2d=noisy), data)
    camera = example_camera()
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"K": camera.K.tolist(), "image_size": list(camera.image_size)}))
    out = tmp_path / "result.npz"
    assert main(["rectify", str(data), "--camera", str(cam), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    rect = Rectifier.load(K_c=camera.K, image_size=camera.image_size)
    want = rect.rectify_batch(noisy, natural.points_3d, natural.valid, infer_mask=natural.infer_mask)
    assert want.fallback_code[0] == "out_of_range"
    assert [f["fallback_code"] for f in report["frames"]] == list(want.fallback_code)
    assert [f["fallback"] for f in report["frames"]] == list(want.fallback)
    with np.load(out, allow_pickle=False) as npz:
        assert npz["fallback_code"].tolist() == [c or "" for c in want.fallback_code]
        assert npz["fallback"].tolist() == [f or "" for f in want.fallback]
