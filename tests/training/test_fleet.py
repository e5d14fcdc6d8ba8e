"""`dimenet fleet train` on the engine (runtime/jobs/engine.py; the engine alone: tests/jobs/test_engine.py): a
manifest of jobs, each the same `dimenet train`, run here or as Ray jobs; resume, a failing job, and the same
results."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import pytest

pytest.importorskip("torch")

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.grid import Grid
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


def test_a_bundled_model_s_name_is_an_init_and_anything_else_a_path_beside_the_manifest(tmp_path):
    jobs = [{"name": n, "dataset": "x.npz", "init": init} for n, init in (("a", "default"), ("b", "any-scene"))]
    jobs.append({"name": "c", "dataset": "x.npz", "init": "./any-scene"})
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"jobs": jobs}))
    assert [job.init for job in read_manifest(path)] == ["default", "any-scene", str(tmp_path / "any-scene")]


def test_bad_manifests_name_the_job_and_the_field(tmp_path):
    cases = {
        '{"jobs": []}': "jobs must be a list of 1 to",
        '{"jobs": [{"dataset": "x.npz"}]}': "job 0: no 'name'",
        '{"jobs": [{"name": "../x", "dataset": "x.npz"}]}': "a folder name",
        '{"jobs": [{"name": "a", "dataset": "x"}, {"name": "a", "dataset": "y"}]}': "job 1 ('a'): name 'a' is used",
        '{"jobs": [{"name": "a", "dataset": "x", "lr": 1}]}': "'lr' is not a job field",
        '{"jobs": [{"name": "a", "dataset": "x", "epochs": 0}]}': "job 0 ('a'): epochs: must be >= 1, got 0",
        '{"jobs": [{"name": "a", "dataset": "x", "grid": 8}]}': "grid must be a string",
        '{"jobs": [{"name": "a", "dataset": "x", "data_step": 1}]}': "data_step must be true or false",
        "[1]": "the manifest must be an object",
    }
    for text, message in cases.items():
        path = tmp_path / "m.json"
        path.write_text(text)
        with pytest.raises(ManifestError, match=re.escape(message)):
            read_manifest(path)
    with pytest.raises(ManifestError, match="absent.json: cannot read the fleet manifest"):
        read_manifest(tmp_path / "absent.json")


# Issue 33: a manifest value the command line refuses: (manifest key, JSON text, `dimenet train` flag).
PAST_THE_CAPS = [
    ("epochs", "1000000000000", "--epochs"),
    ("epochs", "1.5", "--epochs"),
    ("seed", "18446744073709551616", "--seed"),
    ("seed", "-1", "--seed"),
    ("focal_weight", "1e300", "--focal-weight"),
    ("focal_weight", "Infinity", "--focal-weight"),
    ("focal_weight", "-0.5", "--focal-weight"),
    ("grid", '"1000x1000"', "--grid"),
    ("grid", '"abc"', "--grid"),
    ("features", '"Z"', "--features"),
    ("train_frames", "1000000000000000", "--train-frames"),
    ("train_frames", "1", "--train-frames"),
    ("k_c_error", "1.5", "--k-c-error"),
    ("k_c_error", "-0.1", "--k-c-error"),
    ("plane_share", "1.5", "--plane-share"),
]


@pytest.mark.parametrize(("key", "text", "flag"), PAST_THE_CAPS)
def test_a_manifest_passes_nothing_the_command_line_refuses(tmp_path, capsys, key, text, flag):
    path = tmp_path / "m.json"
    path.write_text(f'{{"jobs": [{{"name": "a", "dataset": "x.npz", "{key}": {text}}}]}}')
    with pytest.raises(ManifestError, match=rf"m\.json: job 0 \('a'\): {key}"):
        read_manifest(path)
    value = json.loads(text) if text != "Infinity" else float("inf")
    assert main(["train", "x.npz", "--out", str(tmp_path / "run"), flag, str(value)]) == 2
    assert f"argument {flag}" in capsys.readouterr().err


def test_manifest_values_within_the_caps_are_the_command_line_s(tmp_path):
    path = tmp_path / "m.json"
    job = {"name": "a", "dataset": "x.npz", "epochs": 100000, "seed": 2**32 - 1, "focal_weight": 1000}
    path.write_text(json.dumps({"jobs": [{**job, "grid": "64x64", "features": "E", "train_frames": 2}]}))
    (config,) = [j.config for j in read_manifest(path)]
    scene_options = {"data_step": True, "moments": True, "k_c_error": 1, "plane_share": 0.05}
    path.write_text(json.dumps({"jobs": [{**job, **scene_options}]}))
    (scenes,) = [j.config for j in read_manifest(path)]
    assert (scenes.features.data_step, scenes.features.moments, scenes.k_c_error, scenes.plane_share) == (
        True,
        True,
        1.0,
        0.05,
    )
    assert (config.epochs, config.seed, config.focal_weight, config.train_frames) == (100000, 2**32 - 1, 1000.0, 2)
    assert config.features == FeatureSpec(Grid(64, 64), "E")


@pytest.mark.parametrize("name", ["summary.json", "summary.md", "SUMMARY.JSON", "Summary.Md"])
def test_a_job_may_not_be_named_as_a_file_the_fleet_writes(tmp_path, name):
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"jobs": [{"name": name, "dataset": "x.npz"}]}))
    with pytest.raises(ManifestError, match=rf"job 0 \('{re.escape(name)}'\): name .* is a file the fleet writes"):
        read_manifest(path)


def test_job_names_differing_only_in_case_collide(tmp_path):
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"jobs": [{"name": "s8", "dataset": "x.npz"}, {"name": "S8", "dataset": "y.npz"}]}))
    with pytest.raises(ManifestError, match=r"job 1 \('S8'\): name 'S8' is used twice, in any case"):
        read_manifest(path)


@pytest.fixture(scope="module")
def two_datasets(tmp_path_factory):
    folder = tmp_path_factory.mktemp("resume")
    for p, ds in simulate_family(2, 5, frames=(10, 3)):
        write_dataset(ds, folder / f"{p.name}.npz")
    return sorted(folder.glob("*.npz"))


def _one_job(folder, dataset, **options):
    path = folder / "m.json"
    path.write_text(json.dumps({"jobs": [{"name": "a", "dataset": str(dataset), "epochs": 1, **options}]}))
    return path


def _row(summary):
    (row,) = summary["jobs"]
    assert row["error"] is None, row["error"]
    return row


def test_a_fleet_resumes_only_a_job_whose_config_and_dataset_are_unchanged(two_datasets, tmp_path):
    out, data = tmp_path / "out", tmp_path / "job.npz"
    shutil.copyfile(two_datasets[0], data)
    first = _row(fleet_train(_one_job(tmp_path, data), out))
    assert first["resumed"] is False and "retrained_because" not in first
    record = json.loads((out / "a" / FLEET_FILE).read_text())
    assert record["config"]["epochs"] == 1 and len(record["dataset_sha256"]) == 64
    assert _row(fleet_train(_one_job(tmp_path, data), out))["resumed"] is True
    again = _row(fleet_train(_one_job(tmp_path, data, epochs=2, seed=3), out))
    assert again["resumed"] is False and again["retrained_because"] == "config changed: epochs 1 -> 2, seed 0 -> 3"
    assert "trained again: config changed: epochs 1 -> 2, seed 0 -> 3" in (out / "summary.md").read_text()
    assert json.loads((out / "a" / FLEET_FILE).read_text())["config"]["epochs"] == 2
    shutil.copyfile(two_datasets[1], data)  # the same path, other frames
    changed = _row(fleet_train(_one_job(tmp_path, data, epochs=2, seed=3), out))
    assert changed["resumed"] is False and changed["retrained_because"] == "dataset changed"
    assert _row(fleet_train(_one_job(tmp_path, data, epochs=2, seed=3), out))["resumed"] is True


def test_a_run_finished_without_the_record_is_trained_again_and_says_why(two_datasets, tmp_path):
    out = tmp_path / "out"
    manifest = _one_job(tmp_path, two_datasets[0])
    fleet_train(manifest, out)
    record = json.loads((out / "a" / FLEET_FILE).read_text())
    old = {k: v for k, v in record.items() if k not in ("config", "dataset_sha256")}
    (out / "a" / FLEET_FILE).write_text(json.dumps(old))  # as an earlier release wrote it
    row = _row(fleet_train(manifest, out))
    assert row["resumed"] is False and "without a record of its configuration" in row["retrained_because"]
    assert _row(fleet_train(manifest, out))["resumed"] is True


def test_ray_jobs_give_the_same_models_and_the_same_family(manifest, tmp_path):
    pytest.importorskip("ray")
    ray_run = fleet_train(manifest, tmp_path / "ray", address="local:2")
    local = fleet_train(manifest, tmp_path / "local")
    assert ray_run["failed"] == local["failed"] == ["broken"]
    for r, s in zip(ray_run["jobs"], local["jobs"]):
        assert r.get("rho") == s.get("rho") and r.get("avg_e") == s.get("avg_e")
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
