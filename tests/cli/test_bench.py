"""`dimenet bench`: the report's keys and the budget exit code (no timing assertions)."""

from __future__ import annotations

import json

from dimenet.runtime.cli.main import main


def test_bench_json_reports_every_key(model_path, capsys):
    model = [] if model_path is None else ["--model", str(model_path)]
    assert main(["bench", *model, "--frames", "12", "--points", "64", "--batch", "4", "--callers", "2", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["callers"] == 2 and report["callers_frames_per_s"] > 0
    assert report["callers_speedup"] == report["callers_frames_per_s"] / report["single_frames_per_s"]
    for key in ("end_to_end_us", "baseline_solvepnp_us"):
        assert set(report[key]) == {"p50", "p90", "p99", "max"}
    assert set(report["stages_us"]) == {"validate", "pnp_kc", "features", "model", "pnp_k", "check"}
    assert report["ratio_p50"] > 0 and report["batch_frames_per_s"] > 0 and report["threads"] == 1
    assert len(report["model_sha256"]) == 64 and report["ort_version"] and report["cpu_model"]
    assert report["frames"] == 12 and report["points"] == 64


def test_budget_exceeded_exits_1_and_refine_adds_its_stage(model_path, capsys):
    model = [] if model_path is None else ["--model", str(model_path)]
    assert main(["bench", *model, "--frames", "3", "--points", "32", "--refine", "--budget-ms", "0.000001"]) == 1
    out = capsys.readouterr().out
    assert "stage refine" in out and "exceeds the budget" in out


def test_bench_map_mode_times_its_map_stage(map_model, capsys):
    _, path = map_model
    assert main(["bench", "--model", str(path), "--mode", "map", "--frames", "6", "--points", "64", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["mode"] == "map" and "map" in report["stages_us"] and report["ratio_p50"] > 0
