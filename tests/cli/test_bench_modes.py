"""`dimenet bench --ingest`, `--bpnp` and `--fuzz`: one command, options refused outside their
bench, and --bpnp's one-line error without torch (no timing assertions)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from helpers import importable

from dimenet.runtime.cli.commands import bench as bench_command
from dimenet.runtime.cli.main import main
from dimenet.runtime.rectify.model import bundled_source


def run_without_torch(*args: str) -> subprocess.CompletedProcess:
    code = (
        "import sys; sys.modules['torch'] = None\n"  # import torch raises ImportError, as without the extra
        "from dimenet.runtime.cli.main import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)


def test_bench_help_shows_every_bench_and_ends_with_their_examples(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "--ingest DIR" in out and "--bpnp" in out and "--fuzz N" in out and "--stream N" in out
    assert "(default 2000; with --bpnp 32)" in out
    example = out[out.index("example:") :].splitlines()[1:]
    assert [line.split()[:3] for line in example] == [
        ["dimenet", "bench", "--points"],
        ["dimenet", "bench", "--ingest"],
        ["dimenet", "bench", "--bpnp"],
        ["dimenet", "bench", "--fuzz"],
        ["dimenet", "bench", "--stream"],
    ]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--ingest", "shots", "--bpnp"], "--ingest and --bpnp exclude each other"),
        (["--bpnp", "--model", "m.onnx"], "--model applies only to the latency bench"),
        (["--ingest", "shots", "--frames", "3"], "--frames applies only to the latency bench"),
        (["--n", "3"], "--n applies only to --ingest"),
        (["--repeats", "3"], "--repeats applies only to --bpnp"),
        (["--ingest", "shots", "--n", "0"], "--n: must be >= 1"),
    ],
)
def test_bench_refuses_an_option_of_another_bench_in_one_line(args, message, capsys, every_extra_present):
    assert main(["bench", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_bench_bpnp_without_torch_is_one_line_naming_the_train_extra():
    done = run_without_torch("bench", "--bpnp", "--repeats", "1")
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert lines[0].startswith("dimenet: error: dimenet bench --bpnp needs torch") and "[train]" in lines[0]


@pytest.mark.usefixtures("every_extra_present")
def test_bench_bpnp_without_its_entry_point_is_one_line_naming_the_train_extra(monkeypatch, capsys):
    monkeypatch.setattr(bench_command, "entry_points", lambda group: {})  # an install without the training package
    assert main(["bench", "--bpnp", "--repeats", "1"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "--bpnp: no bpnp bench is registered: " in lines[0] and "[train]" in lines[0], lines


def test_bench_without_torch_still_runs_its_help():
    done = run_without_torch("bench", "--help")
    assert done.returncode == 0 and "dimenet bench --bpnp" in done.stdout, done.stderr


def test_bench_fuzz_reports_every_area_and_exits_0_without_findings(capsys):
    assert main(["bench", "--fuzz", "12", "--seed", "3", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["model"] == bundled_source("default")
    assert set(report["counts"]) == {
        "rectify",
        "stream",
        "rectify_batch",
        "dataset file",
        "model file",
        "rig file",
        "camera file",
        "points file",
        "gyroscope file",
        "lens-shift file",
        "crafted model",
    } | {
        area for area, modules in (("full graph", ("onnx",)), (".ort file", ("onnx", "torch"))) if importable(*modules)
    }
    assert len(report["skipped"]) == 2 - importable("onnx") - importable("onnx", "torch")  # a line per area skipped
    assert sum(report["counts"]["rectify"].values()) == 24  # 12 per mode
    assert report["failures"] == [] and all("crash" not in c for c in report["counts"].values())
    assert main(["bench", "--fuzz", "3", "--bpnp"]) == 2


def test_bench_fuzz_runs_the_model_asked_for(capsys):
    assert main(["bench", "--fuzz", "6", "--seed", "3", "--model", "paper-rig"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("model bundled paper-rig model (paper_rig_model.onnx)\n"), out
    assert main(["bench", "--fuzz", "3", "--model", "missing.onnx"]) == 2
    assert "missing.onnx: no such model file" in capsys.readouterr().err


def test_bench_ingest_never_renders_into_a_folder_of_other_files(tmp_path, capsys):
    (tmp_path / "IMG_0001.jpg").write_bytes(b"a photo of something else")
    assert main(["bench", "--ingest", str(tmp_path), "--n", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "neither truth.npz" in err[0] and "rig.json" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["IMG_0001.jpg"]
