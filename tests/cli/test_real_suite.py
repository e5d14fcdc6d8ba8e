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
@pytest.mark.parametrize("model", ["default", "any-scene"])
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
