"""`dimenet rectify` (and the torch-free import of the runtime and its rectify/bench commands)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from helpers import example_camera

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import write_dataset


def test_runtime_and_its_commands_never_import_torch_or_onnx():
    code = (
        "import sys\n"
        "import dimenet.runtime, dimenet.runtime.rectify.rectifier, dimenet.runtime.rectify.model\n"
        "import dimenet.runtime.bench.latency\n"
        "from dimenet.runtime.cli.main import main\n"
        "for cmd in ('rectify', 'bench'):\n"
        "    try:\n"
        "        main([cmd, '--help'])\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code == 0, exc.code\n"
        "heavy = sorted(m for m in ('torch', 'onnx') if m in sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "dimenet rectify" in done.stdout and "dimenet bench" in done.stdout


def test_rectify_command_on_the_example_and_on_a_dataset(model_path, frames, tmp_path, capsys):
    model = [] if model_path is None else ["--model", str(model_path)]
    out = tmp_path / "result.npz"
    assert main(["rectify", "--example", *model, "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert len(report["frames"]) == 8 and report["summary"]["n_frames"] == 8
    with np.load(out, allow_pickle=False) as npz:
        assert npz["K"].shape == (8, 3, 3) and npz["fallback"].dtype.kind == "U"
        assert np.all(np.isfinite(npz["e"])) and np.all(np.isfinite(npz["e_c"]))
        np.testing.assert_allclose(npz["e"], [f["e_px"] for f in report["frames"]])
        assert npz["fallback_code"].tolist() == [f["fallback_code"] or "" for f in report["frames"]]
    data = tmp_path / "natural.npz"
    write_dataset(frames.select(frames.scene == "natural"), data)
    camera_file = []
    if model_path is None:  # the generic default needs the camera: no train split to calibrate it from
        camera = example_camera()
        cam = tmp_path / "cam.json"
        cam.write_text(json.dumps({"K": camera.K.tolist(), "image_size": list(camera.image_size)}))
        camera_file = ["--camera", str(cam)]
    assert main(["rectify", str(data), *model, *camera_file]) == 0
    assert "3 frames: Avg(e_c)" in capsys.readouterr().out
    other = replace(frames.select(frames.scene == "natural"), image_size=np.array([4000, 3000]))
    write_dataset(other, tmp_path / "other.npz")
    assert main(["rectify", str(tmp_path / "other.npz"), *model]) == 2
    assert "needs the camera's K_c: give --camera FILE" in capsys.readouterr().err
    assert main(["rectify"]) == 2


@pytest.mark.parametrize("bundled", ["default", "paper-rig"])
def test_rectify_command_mode_map_writes_k_cov(model_path, tmp_path, capsys, bundled):
    """Each bundled model carries an uncertainty model: mode map fits the frames' points at least
    as well as mode dimenet and reports K_cov (npz) and its standard deviations (JSON)."""
    results = {}
    for mode in ("dimenet", "map"):
        out = tmp_path / f"{mode}.npz"
        args = ["rectify", "--example", "--model", bundled, "--mode", mode, "--out", str(out), "--json"]
        assert main(args) == 0
        report = json.loads(capsys.readouterr().out)
        assert report["mode"] == mode and report["summary"]["fallbacks"] == 0
        with np.load(out, allow_pickle=False) as npz:
            results[mode] = {k: npz[k] for k in npz.files}
        for i, frame in enumerate(report["frames"]):
            np.testing.assert_allclose(frame["K_sigma_px"], np.sqrt(np.diag(results[mode]["K_cov"][i])))
            assert all(s > 0 for s in frame["K_sigma_px"])
    assert results["map"]["e"].mean() < results["dimenet"]["e"].mean()
    if bundled == "paper-rig":  # the data add information to the grid model's prior; the default's map
        # covariance, fitted against the true K, is wider than its network's on these frames (METHOD.md)
        assert np.all(
            np.diagonal(results["map"]["K_cov"], axis1=1, axis2=2)
            < np.diagonal(results["dimenet"]["K_cov"], axis1=1, axis2=2)
        )
    if model_path is not None:  # a model without an uncertainty model cannot fuse: one line, exit 2
        assert main(["rectify", "--example", "--model", str(model_path), "--mode", "map"]) == 2
        assert "no uncertainty model" in capsys.readouterr().err
