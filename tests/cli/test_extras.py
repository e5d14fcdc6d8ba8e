"""Missing extras (runtime/cli/extras.py): every command, with the arguments that bring a need, names the
one install that makes it work, from the one table; the extras' modules are pyproject.toml's; a command
the table gives no need runs with every extra missing. Modules are made missing in a fresh process
(``sys.modules[name] = None``: ``import name`` fails and ``find_spec`` finds nothing, as without them)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import importable

from dimenet.runtime.cli.extras import EXTRAS, NEEDS

ROOT = Path(__file__).resolve().parents[2]
EVERY_EXTRA = ("torch", "safetensors", "matplotlib", "onnx", "ray")
CPU = "pip install torch --index-url https://download.pytorch.org/whl/cpu, then "
TRAIN = (
    "needs torch, safetensors, matplotlib, onnx (the train extra): "
    + CPU
    + ("pip install 'dimenet-runtime[train]' (in a checkout: pip install '.[train]')")
)
TRAIN_FLEET = (
    "needs torch, safetensors, matplotlib, onnx, ray (the train extra and the fleet extra): "
    + CPU
    + ("pip install 'dimenet-runtime[train,fleet]' (in a checkout: pip install '.[train,fleet]')")
)
FLEET = "needs ray (the fleet extra): pip install 'dimenet-runtime[fleet]' (in a checkout: pip install '.[fleet]')"
EXPORT = "needs onnx (the export extra): pip install 'dimenet-runtime[export]' (in a checkout: pip install '.[export]')"

# (command line, the one line it must print) with every extra missing; RUN_DIR is an existing folder.
WITHOUT_EXTRAS = [
    (["train", "s8.npz", "--out", "runs/s8"], "dimenet train " + TRAIN),
    (["train", "family", "--out", "runs/generic", "--init", "default"], "dimenet train " + TRAIN),
    (["reproduce", "--out", "reproduction"], "dimenet reproduce " + TRAIN),
    (["reproduce", "--out", "reproduction", "--address", "local:2"], "dimenet reproduce --address " + TRAIN_FLEET),
    (["fleet", "train", "devices.json", "--out", "fleet"], "dimenet fleet " + TRAIN),
    (
        ["fleet", "train", "devices.json", "--out", "fleet", "--address", "auto"],
        "dimenet fleet --address " + TRAIN_FLEET,
    ),
    (["simulate", "--family", "2", "--out", "family", "--address", "local:2"], "dimenet simulate --address " + FLEET),
    (["evaluate", "s8.npz", "--model", "RUN_DIR"], "dimenet evaluate --model RUN_DIR " + TRAIN),
    (["bench", "--bpnp", "--repeats", "1"], "dimenet bench --bpnp " + TRAIN),
    (["export", "RUN_DIR", "--out", "s8.onnx"], "dimenet export RUN_DIR " + TRAIN),
    (["export", "RUN_DIR", "--graph", "full", "--out", "f.onnx"], "dimenet export RUN_DIR --graph full " + TRAIN),
    (["export", "default", "--format", "ort", "--out", "d.ort"], "dimenet export --format ort " + TRAIN),
    (["export", "default", "--graph", "full", "--out", "f.onnx"], "dimenet export --graph full " + EXPORT),
]


def run_without(blocked: tuple, argvs: list, cwd: Path) -> list:
    """[(exit code, stderr)] of ``dimenet ARGV`` for each of ``argvs``, in one process where ``blocked``
    cannot be imported."""
    code = (
        "import contextlib, io, json, sys\n"
        "for name in sys.argv[1].split(','): sys.modules[name] = None\n"
        "from dimenet.runtime.cli.main import main\n"
        "out = []\n"
        "for argv in json.loads(sys.argv[2]):\n"
        "    err = io.StringIO()\n"
        "    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):\n"
        "        out.append((main(argv), err.getvalue()))\n"
        "print(json.dumps(out))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, ",".join(blocked), json.dumps(argvs)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_every_command_names_the_one_install_from_the_table(tmp_path):
    (tmp_path / "RUN_DIR").mkdir()
    results = run_without(EVERY_EXTRA, [argv for argv, _ in WITHOUT_EXTRAS], tmp_path)
    for (argv, expected), (code, err) in zip(WITHOUT_EXTRAS, results):
        assert code == 2 and err.splitlines() == [f"dimenet: error: {expected}"], (argv, err)


def test_every_row_of_the_table_is_held_by_a_case():
    """A need added to the table without a case here fails: each (command, extra, when) appears."""
    rows = {(command, n.extra, n.when) for command, needs in NEEDS.items() for n in needs}
    held = set()
    for argv, line in WITHOUT_EXTRAS:
        words = line.split(" needs ")[0].split()[2:]  # the arguments the line names
        held |= {(argv[0], n.extra, n.when) for n in NEEDS[argv[0]] if n.when in ("", *words, " ".join(words))}
    assert rows <= held, rows - held


def test_an_install_names_only_what_is_missing_and_torch_first_only_when_torch_is(tmp_path):
    """With the train extra there and Ray missing, --address asks for the fleet extra alone; export's
    full graph of a bundled model runs on onnx alone (it needs no torch, safetensors or matplotlib)."""
    if not importable(*EXTRAS["train"]):
        pytest.skip("the train extra is not installed (this test makes only Ray missing)")
    argvs = [
        ["reproduce", "--out", "reproduction", "--address", "local:2"],
        ["fleet", "train", "devices.json", "--out", "fleet", "--address", "local:2"],
    ]
    results = run_without(("ray",), argvs, tmp_path)
    assert [r[1].splitlines() for r in results] == [
        ["dimenet: error: dimenet reproduce --address " + FLEET],
        ["dimenet: error: dimenet fleet --address " + FLEET],
    ]
    full = ["export", "default", "--graph", "full", "--out", str(tmp_path / "full.onnx")]
    (code, err), *_ = run_without(("torch", "safetensors", "matplotlib", "ray"), [full], tmp_path)
    assert code == 0 and (tmp_path / "full.onnx").stat().st_size > 0, err


def test_commands_without_a_need_run_with_every_extra_missing(tmp_path):
    argvs = [
        ["rectify", "--example", "--json"],
        ["export", "default", "--golden", str(tmp_path / "golden")],
        ["simulate", "--profile", "galaxy-s8", "--out", str(tmp_path / "s8.npz")],
        ["evaluate", str(tmp_path / "s8.npz"), "--model", "default"],
    ]
    for argv, (code, err) in zip(argvs, run_without(EVERY_EXTRA, argvs, tmp_path)):
        assert code == 0, (argv, err)


def test_the_extras_modules_are_pyprojects():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11 (the floors run 3.9)
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["optional-dependencies"]
    listed = {name: tuple(re.match(r"[A-Za-z0-9_-]+", r).group() for r in reqs) for name, reqs in extras.items()}
    assert {name: mods for name, mods in listed.items() if name != "dev"} == EXTRAS
