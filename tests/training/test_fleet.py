"""`dimenet fleet train` on the engine (runtime/jobs/engine.py; the engine alone: tests/jobs/test_engine.py): a
manifest of jobs, each the same `dimenet train`, run here or as Ray jobs; resume, a failing job, and the same
results."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time

import pytest

pytest.importorskip("torch")

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.sim.family import simulate_family
from dimenet.training.fleet import FLEET_FILE, ManifestError, fleet_train, read_manifest


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    """Two tiny jobs (2 epochs, 20 frames) and one whose dataset does not exist."""
    folder = tmp_path_factory.mktemp("fleet")
    for p, ds in simulate_family(2, 9, frames=(16, 4)):
        write_dataset(ds, folder / f"{p.name}.npz")
    jobs = [
        {"name": "a", "dataset": "family-s9-000.npz", "epochs": 2, "seed": 1},
        {"name": "b", "dataset": "family-s9-001.npz", "epochs": 2, "init": "default", "train_frames": 10},
        {"name": "broken", "dataset": "missing.npz", "epochs": 2},
    ]
    path = folder / "manifest.json"
    path.write_text(json.dumps({"jobs": jobs}))
    return path


def test_a_fleet_trains_every_job_reports_the_broken_one_and_resumes(manifest, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["fleet", "train", str(manifest), "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert "failed: broken" in captured.err and "missing.npz: no such dataset file" in captured.out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failed"] == ["broken"]
    done = {r["name"]: r for r in summary["jobs"] if r["error"] is None}
    assert set(done) == {"a", "b"} and all(0 <= r["rho"] <= 1.01 or r["rho"] < 0 for r in done.values())
    assert (out / "a" / "spec.json").is_file() and (out / "b" / FLEET_FILE).is_file()
    assert not list(out.glob(".*.partial"))
    # A job killed mid-way left a partial folder; the next run redoes it and reads the others.
    (out / "a").rename(out / ".a.partial")
    again = fleet_train(manifest, out)
    status = {r["name"]: r.get("resumed") for r in again["jobs"]}
    assert status == {"a": False, "b": True, "broken": None}
    rows = {r["name"]: r for r in again["jobs"]}
    assert rows["a"]["rho"] == pytest.approx(done["a"]["rho"])  # the same seed, the same model


def test_bad_manifests_name_the_job_and_the_field(tmp_path):
    cases = {
        '{"jobs": []}': "jobs must be a list of 1 to",
        '{"jobs": [{"dataset": "x.npz"}]}': "job 0: no 'name'",
        '{"jobs": [{"name": "../x", "dataset": "x.npz"}]}': "a folder name",
        '{"jobs": [{"name": "a", "dataset": "x"}, {"name": "a", "dataset": "y"}]}': "job 1 ('a'): name 'a' is used",
        '{"jobs": [{"name": "a", "dataset": "x", "lr": 1}]}': "'lr' is not a job field",
        '{"jobs": [{"name": "a", "dataset": "x", "epochs": 0}]}': "epochs must be",
        '{"jobs": [{"name": "a", "dataset": "x", "grid": 8}]}': "grid must be a string",
        "[1]": "the manifest must be an object",
    }
    for text, message in cases.items():
        path = tmp_path / "m.json"
        path.write_text(text)
        with pytest.raises(ManifestError, match=re.escape(message)):
            read_manifest(path)
    with pytest.raises(ManifestError, match="absent.json: cannot read the fleet manifest"):
        read_manifest(tmp_path / "absent.json")


def test_ray_jobs_give_the_same_models_and_the_same_family(manifest, tmp_path):
    pytest.importorskip("ray")
    start = time.monotonic()
    ray_run = fleet_train(manifest, tmp_path / "ray", address="local:2")
    local = fleet_train(manifest, tmp_path / "local")
    assert ray_run["failed"] == local["failed"] == ["broken"]
    for r, s in zip(ray_run["jobs"], local["jobs"]):
        assert r.get("rho") == s.get("rho") and r.get("avg_e") == s.get("avg_e")
    assert time.monotonic() - start < 120
    for address in (None, "local:2"):
        out = tmp_path / f"family-{address}"
        argv = ["simulate", "--family", "3", "--seed", "4", "--out", str(out)]
        assert main(argv + ([] if address is None else ["--address", address])) == 0
    for name in ("family-s4-000.npz", "family-s4-001.npz", "family-s4-002.npz"):  # byte-identical per seed
        assert (tmp_path / "family-None" / name).read_bytes() == (tmp_path / "family-local:2" / name).read_bytes()


def test_nothing_imports_ray_until_an_address_asks_for_it():
    code = (
        "import sys, dimenet.runtime.cli.main, dimenet.runtime.jobs.engine, dimenet.training.trainer, "
        "dimenet.training.fleet, dimenet.training.commands; print('ray' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0 and done.stdout.strip() == "False", done.stderr
