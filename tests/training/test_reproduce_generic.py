"""`dimenet reproduce`'s generic rows (training/reproduce/generic.py) on small inputs: every row
is computed and reported, for the bundled paper-rig model and a device model beside it."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from helpers import DEVICE_MODEL

from dimenet.runtime.evaluation.predictor import load_onnx_predictor
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.sim.simulator import simulate
from dimenet.training.config import ReproduceConfig
from dimenet.training.init_weights import initial_weights
from dimenet.training.reproduce import generic
from dimenet.training.reproduce.report import _generic_report
from dimenet.training.trainer import train


def test_the_generic_rows_are_computed_and_reported(tmp_path, monkeypatch):
    monkeypatch.setattr(generic, "DEVICES", ("galaxy-s8",))
    monkeypatch.setattr(generic, "FRESH_FAMILY_CAMERAS", 2)
    monkeypatch.setattr(generic, "FINE_TUNE_FRAMES", 20)
    monkeypatch.setattr(generic, "FRESH_SCENES", {"rig": (101, 2, (0.2, 0.8)), "far": (202, 1, (0.2, 1 / 3))})
    monkeypatch.setattr(generic, "OIS_OFF_FAMILY", (11, 2))  # its camera 1 has no OIS
    monkeypatch.setattr(generic, "FRESH_NATURAL", (404, 4, 8))  # camera 3 has a gap past noise
    data = {"galaxy-s8": simulate("galaxy-s8", seed=2, natural_frames=4, planar_frames=4)}
    device = {"galaxy-s8": load_onnx_predictor(DEVICE_MODEL)}
    config = ReproduceConfig(out_dir=tmp_path, epochs=2)
    dataset, cfg, run_dir, init = generic.fine_tune_training(data, tmp_path, config)
    tuned = train(dataset, cfg, run_dir, init=initial_weights(init))
    side = {
        "fine_tune": (tuned.run_dir, tuned.seconds),
        "fresh_family": generic.fresh_family(),
        "fresh_scenes": {name: generic.fresh_scenes(name) for name in ("paper-rig", "default")},
    }
    results = generic.run_generic(data, device, config, load_model(generic.GENERIC_MODEL), side)
    rows = results["zero_shot"]
    assert set(rows) == {"galaxy-s8 rig", "galaxy-s8 rig 64 pts", "galaxy-s8 natural", "galaxy-s8 planar"}
    assert rows["galaxy-s8 rig"]["generic"]["dimenet"] > 0.9 and rows["galaxy-s8 rig"]["device"]["dimenet"] > 0.9
    assert len(results["fresh_family"]) == 2 and all(r["rho"] > 0.5 for r in results["fresh_family"])
    assert set(results["fine_tune"]["rows"]) == {"rig 64 pts", "natural"}
    assert set(results["fresh_scenes"]) == {"paper-rig", "default"}
    scenes = results["fresh_scenes"]["paper-rig"]
    assert [len(scenes[name]) for name in ("rig", "far", "natural")] == [2, 1, 4]
    assert all(r["kind"] in ("room", "buildings", "objects") and r["features"] >= 15 for r in scenes["natural"])
    assert any(r["all"]["map"] is not None for r in scenes["natural"])
    # beside the modes on natural frames, the prior oracle and each mode's rho over it with its interval (issue 50)
    assert all(set(r["ratio"]) == {"dimenet", "map"} and r["label_noise_px"] > 0 for r in scenes["natural"])
    assert any(r["prior_oracle"] is not None and r["ratio"]["map"]["level"] == 0.9 for r in scenes["natural"])
    assert "generic_prior_oracle" in rows["galaxy-s8 natural"] and "generic_ratio" not in rows["galaxy-s8 rig"]
    # the bundled model on random rigs: better than K_c in mode map (the frame's points carry it), every case measured
    assert all(
        r[case]["map"] > 0.3 for rows in (scenes["rig"], scenes["far"]) for r in rows for case in ("all", "small")
    )
    assert scenes["ois_off"]["cameras"] == 1 and scenes["ois_off"]["frames"] == 20
    assert all(0.0 <= v <= 1.0 for key in ("within", "within_true") for v in scenes["ois_off"][key].values())
    inv = results["invariance"]
    assert inv["half_vs_full_mean_px"] < 1e-6 and inv["m_vs_mm_max_px"] < 1e-6
    assert inv["half_points_full_k_c_silent"] == 0
    text = "\n".join(_generic_report(results))
    assert "## The paper's grid model (paper-rig, generic) beside the per-device ones" in text
    assert "family-s101-001" in text
    assert "### Held-out scene families" in text and "Cameras without OIS (1 of" in text
    assert "| far | 1 | paper-rig |" in text and "| far | 1 | default |" in text
    assert "| natural | 4 | default |" in text and "- the default model: " in text
    assert "against the **prior oracle**" in text and "| default | family-s404-003 |" in text
    assert "moves from K_c by at most 2σ" in text and "within 2σ of K_true" in text
    # the default (any-scene) reads the frame's own step: on the held-out rigs it beats K_c in mode dimenet too
    assert all(r["all"]["dimenet"] > 0.5 for r in results["fresh_scenes"]["default"]["rig"])
    assert np.isfinite(rows["galaxy-s8 planar"]["generic"]["map"])
