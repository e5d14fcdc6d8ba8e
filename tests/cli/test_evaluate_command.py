"""`dimenet evaluate --methods`: JSON and table output, and its one-line errors."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.sim.simulator import simulate


def test_evaluate_methods_json_and_table(map_model, tmp_path, capsys):
    frames, path = map_model
    data = write_dataset(frames, tmp_path / "d.npz")
    assert main(["evaluate", str(data), "--model", str(path), "--methods", "kc,self,dimenet,map,oracle", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    methods = out["methods"]
    # beside the modes on natural frames, the prior oracle (the simulator records the label noise it needs)
    assert list(methods) == ["kc", "self", "dimenet", "map", "oracle", "prior-oracle"]
    assert set(methods["map"]) == {"rig", "natural", "planar", "overall"}
    assert methods["kc"]["overall"]["rho"] == pytest.approx(0.0, abs=1e-12)
    assert methods["oracle"]["overall"]["rho"] == pytest.approx(1.0, abs=1e-12)
    assert methods["self"]["rig"]["rho"] > 0.95
    assert methods["dimenet"]["overall"]["avg_e"] == pytest.approx(out["overall"]["avg_e"])
    assert out["fallbacks"]["self"] >= 2  # the planar frames
    assert set(out["coverage"]) == {"dimenet", "map", "prior-oracle"}
    assert set(out["coverage"]["map"]) == {"fx", "fy", "cx", "cy"}
    assert main(["evaluate", str(data), "--model", str(path), "--methods", "self,map"]) == 0
    assert "1-sigma coverage" in capsys.readouterr().out


def test_evaluate_reports_the_prior_oracle_beside_the_modes_on_natural_frames(map_model, tmp_path, capsys):
    frames, path = map_model
    data = write_dataset(frames, tmp_path / "d.npz")
    assert main(["evaluate", str(data), "--model", str(path), "--methods", "dimenet,map"]) == 0
    table = capsys.readouterr().out
    assert "rho / rho(prior-oracle)" in table and "90% interval" in table
    assert any(line.split()[:2] == ["prior-oracle", "natural"] for line in table.splitlines())
    assert main(["evaluate", str(data), "--model", str(path), "--methods", "map", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    ratio = out["ratios_to_prior_oracle"]["map"]["natural"]
    rho, rho_oracle = (out["methods"][m]["natural"]["rho"] for m in ("map", "prior-oracle"))
    assert ratio["level"] == 0.9 and ratio["n_frames"] == 2 and ratio["ratio"] == pytest.approx(rho / rho_oracle)
    # a dataset without the label noise (a user's) still evaluates, and says what the oracle misses
    bare = write_dataset(replace(frames, label_noise_px=None), tmp_path / "bare.npz")
    assert main(["evaluate", str(bare), "--model", str(path), "--methods", "dimenet,map"]) == 0
    table = capsys.readouterr().out
    assert "prior-oracle n/a on the natural frames" in table and "no label_noise_px" in table
    assert main(["evaluate", str(bare), "--methods", "prior-oracle"]) == 2
    assert "label_noise_px" in capsys.readouterr().err


def test_evaluate_methods_errors_exit_2(tmp_path, capsys):
    data = write_dataset(simulate("galaxy-s8", seed=1), tmp_path / "d.npz")
    for argv, message in ((["--methods", "map"], "needs --model"), (["--methods", "kc,fast"], "unknown method 'fast'")):
        assert main(["evaluate", str(data), *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("name", ["default", "paper-rig"])
def test_a_bundled_model_s_name_is_taken_wherever_a_model_is(tmp_path, capsys, name):
    """Issue 34: `train --init default` was accepted while `evaluate --model default` was refused; the
    paper-rig model is named alike."""
    from dimenet.runtime.evaluation.predictor import load_predictor
    from dimenet.runtime.rectify.model import BUNDLED_MODELS, bundled_source, load_model

    data = write_dataset(simulate("galaxy-s8", seed=1), tmp_path / "d.npz")
    assert main(["evaluate", str(data), "--model", name, "--json"]) == 0
    rho = json.loads(capsys.readouterr().out)["overall"]["rho"]
    assert 0.5 < rho <= 1.0
    assert load_predictor(name).source == load_model(name).source == bundled_source(name)
    assert main(["rectify", str(data), "--model", name]) == 0
    assert BUNDLED_MODELS[name] in capsys.readouterr().out
    (tmp_path / name).mkdir()  # a folder of that name is reached as ./NAME
    assert main(["evaluate", str(data), "--model", str(tmp_path / name)]) == 2
