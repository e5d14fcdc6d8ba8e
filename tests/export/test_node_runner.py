"""The Node runner (export/node_runner/run.mjs, CI's second-language check) on the real golden vectors and
on hostile golden files (issue 48, #7 and #8): the real ones pass through the real full graph, a changed
expected value fails with exit 1, and a golden file that cannot be checked (no frames, empty or short
expected arrays, sigma null where the graph has sigma or the reverse, a frame without its pose or inputs,
a mask or 3D points of another count than the 2D points, a non-number) is refused with exit 2 and one line
naming the frame and the field, before anything is compared: never a Node stack trace, never a pass that
checked nothing.

Needs node and export/node_runner/node_modules (`npm ci` there; .ci/run installs them before pytest and
sets DIMENET_REQUIRE_NODE=1, which turns their absence into a failure), and onnx for the full graph."""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RUNNER = ROOT / "export" / "node_runner" / "run.mjs"
GOLDEN = ROOT / "models_spec" / "golden" / "golden.json"
NODE = shutil.which("node")
_missing = "node" if NODE is None else None
if _missing is None and not (RUNNER.parent / "node_modules" / "onnxruntime-node").is_dir():
    _missing = "export/node_runner/node_modules (npm ci there)"
if _missing is not None:
    if os.environ.get("DIMENET_REQUIRE_NODE"):
        raise RuntimeError(f"DIMENET_REQUIRE_NODE is set, but {_missing} is absent")
    pytest.skip(f"the Node runner needs {_missing}", allow_module_level=True)
onnx = pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def graphs(tmp_path_factory) -> dict:
    """The bundled default's full graph, and the same without its sigma output."""
    from dimenet.export.full_graph import full_graph
    from dimenet.runtime.rectify.model import bundled_model_bytes

    folder = tmp_path_factory.mktemp("graphs")
    blob = full_graph(bundled_model_bytes(), "default")
    proto = onnx.load_from_string(blob)
    kept = [o for o in proto.graph.output if o.name != "sigma"]
    assert len(kept) == len(proto.graph.output) - 1
    del proto.graph.output[:]
    proto.graph.output.extend(kept)
    paths = {"full": folder / "full.onnx", "no-sigma": folder / "no-sigma.onnx"}
    paths["full"].write_bytes(blob)
    paths["no-sigma"].write_bytes(proto.SerializeToString())
    return paths


@pytest.fixture(scope="module")
def golden() -> dict:
    return json.loads(GOLDEN.read_text(encoding="utf-8"))


def run(graph: Path, golden_path: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [NODE, str(RUNNER), str(graph), str(golden_path)], capture_output=True, text=True, timeout=120, check=False
    )


def test_the_real_golden_vectors_pass_and_a_changed_value_fails(graphs, golden, tmp_path):
    done = run(graphs["full"], GOLDEN)
    assert done.returncode == 0, done.stderr
    frames = len(golden["frames"])
    values = sum(len(f["expected"]["delta_k"]) + 9 + len(f["expected"]["sigma"]) for f in golden["frames"])
    assert done.stdout.startswith(f"{frames} golden frames ({values} values) through ") and ", 0 failed" in done.stdout
    changed = copy.deepcopy(golden)
    changed["frames"][3]["expected"]["K"][1][2] += 1e-3
    path = tmp_path / "changed.json"
    path.write_text(json.dumps(changed), encoding="utf-8")
    done = run(graphs["full"], path)
    assert done.returncode == 1
    name = golden["frames"][3]["name"]
    assert done.stderr.startswith(f"frame 3 ({name}): K differs by 1.00e-3 px")


def _set(golden: dict, where: str, value) -> dict:
    """A copy of ``golden`` with the field at ``where`` (keys and indices joined by '/') set to ``value``,
    or deleted when ``value`` is DELETE."""
    changed = copy.deepcopy(golden)
    *path, last = [int(k) if k.isdigit() else k for k in where.split("/")]
    parent = changed
    for key in path:
        parent = parent[key]
    if value is DELETE:
        del parent[last]
    else:
        parent[last] = value(parent[last]) if callable(value) else value
    return changed


DELETE = object()
F0 = "frame 0 (galaxy-s8-rig-0)"
HOSTILE = [
    ("frames", [], "frames must be a non-empty array, got []"),
    ("frames", DELETE, "frames must be a non-empty array, got nothing"),
    ("frames/0", 5, "frame 0 must be an object, got 5"),
    ("frames/0/expected/delta_k", [], f"{F0}: expected.delta_k has 0 entries, expected 4"),
    ("frames/0/expected/K", [], f"{F0}: expected.K has 0 entries, expected 3"),
    ("frames/0/expected/sigma", None, f"{F0}: expected.sigma must be an array of 4, got null"),
    ("frames/0/expected/delta_k", lambda v: v[:3], f"{F0}: expected.delta_k has 3 entries, expected 4"),
    ("frames/0/expected/sigma", lambda v: v + [0.0], f"{F0}: expected.sigma has 5 entries, expected 4"),
    ("frames/0/expected/K/2", lambda v: v[:2], f"{F0}: expected.K[2] has 2 entries, expected 3"),
    ("frames/0/expected/rvec", DELETE, f"{F0}: expected.rvec must be an array of 3, got nothing"),
    ("frames/0/expected/tvec", "0", f'{F0}: expected.tvec must be an array of 3, got "0"'),
    ("frames/0/inputs", DELETE, f"{F0}: inputs must be an object, got nothing"),
    (
        "frames/0/inputs/mask",
        [],
        f"{F0}: inputs.mask must be an array of {{n}} booleans (one per 2D point), got 0 entries",
    ),
    ("frames/0/inputs/mask/0", 1, f"{F0}: inputs.mask[0] must be a boolean, got 1"),
    (
        "frames/0/inputs/points_3d",
        lambda v: v[:-1],
        f"{F0}: inputs.points_3d (one per 2D point) has {{m}} entries, expected {{n}}",
    ),
    ("frames/0/inputs/points_2d/5/1", None, f"{F0}: inputs.points_2d[5][1] must be a finite number, got null"),
    ("frames/0/expected/delta_k/2", "0.5", f'{F0}: expected.delta_k[2] must be a finite number, got "0.5"'),
    ("frames/0/inputs/K_c/0/0", True, f"{F0}: inputs.K_c[0][0] must be a finite number, got true"),
    ("frames/21/inputs/image_size", [4032], "frame 21 (noisy): inputs.image_size has 1 entries, expected 2"),
    ("format", "dimenet-golden/2", 'format must be dimenet-golden/1, got "dimenet-golden/2"'),
]


@pytest.mark.parametrize("where, value, message", HOSTILE, ids=[f"{w}-{m[-24:]}" for w, _, m in HOSTILE])
def test_a_golden_file_that_cannot_be_checked_is_one_line_and_exit_2(graphs, golden, tmp_path, where, value, message):
    n = len(golden["frames"][0]["inputs"]["points_2d"])
    path = tmp_path / "hostile.json"
    path.write_text(json.dumps(_set(golden, where, value)), encoding="utf-8")
    done = run(graphs["full"], path)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.splitlines() == [f"run.mjs: {path}: " + message.format(n=n, m=n - 1)]


def test_sigma_in_a_golden_file_for_a_graph_without_sigma_is_refused(graphs, golden, tmp_path):
    done = run(graphs["no-sigma"], GOLDEN)
    assert done.returncode == 2
    assert done.stderr.splitlines() == [
        f"run.mjs: {GOLDEN}: {F0}: expected.sigma is given, but the graph has no sigma output"
    ]
    without = copy.deepcopy(golden)
    for frame in without["frames"]:
        frame["expected"]["sigma"] = None
    path = tmp_path / "no-sigma.json"
    path.write_text(json.dumps(without), encoding="utf-8")
    done = run(graphs["no-sigma"], path)
    assert done.returncode == 0, done.stderr


def test_unreadable_files_and_a_graph_of_another_kind_are_one_line(graphs, tmp_path):
    from dimenet.runtime.rectify.model import bundled_model_bytes

    (tmp_path / "bad.json").write_text('{"format": ', encoding="utf-8")
    (tmp_path / "mlp.onnx").write_bytes(bundled_model_bytes())
    for argv, start in (
        ([graphs["full"], tmp_path / "bad.json"], f"run.mjs: {tmp_path / 'bad.json'}: not a readable JSON file"),
        ([graphs["full"], tmp_path / "none.json"], f"run.mjs: {tmp_path / 'none.json'}: not a readable JSON file"),
        ([tmp_path / "none.onnx", GOLDEN], f"run.mjs: {tmp_path / 'none.onnx'}: not a loadable ONNX model"),
        ([tmp_path / "mlp.onnx", GOLDEN], f"run.mjs: {tmp_path / 'mlp.onnx'}: it takes features: a full graph takes"),
    ):
        done = run(*argv)
        assert done.returncode == 2
        assert len(done.stderr.splitlines()) == 1 and done.stderr.startswith(start), done.stderr
    done = subprocess.run([NODE, str(RUNNER)], capture_output=True, text=True, timeout=60, check=False)
    assert (done.returncode, done.stderr) == (2, "run.mjs: usage: node run.mjs FULL.onnx GOLDEN.json\n")
