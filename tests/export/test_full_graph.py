"""`dimenet export --graph full` (export.full_graph): the whole feature of a generic model in one graph of
standard ONNX operators, within the parity bound of the Python runtime on every golden frame, with a mask, at
any pose, in any unit; masked points that hold anything change nothing, and a frame without a point gives K_c
and the population's sigma (models_spec/model-v1.md, "The full graph's contract"); the golden set's inputs
are what golden_frames() simulates today."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
import onnxruntime as ort  # noqa: E402
from helpers import assert_json_close  # noqa: E402

from dimenet.export.full_graph import INPUTS, OUTPUTS, full_graph  # noqa: E402
from dimenet.export.golden import PARITY_DELTA_PX, PARITY_PX, golden_frames, parity_px  # noqa: E402
from dimenet.runtime.errors import ModelError  # noqa: E402
from dimenet.runtime.geometry import solve_pnp_start  # noqa: E402
from dimenet.runtime.rectify.model import bundled_model_bytes  # noqa: E402
from dimenet.runtime.rectify.rectifier import Rectifier  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
GOLDEN_DIR = ROOT / "models_spec" / "golden"
GOLDEN = GOLDEN_DIR / "golden.json"
NAMED_GOLDEN = {"default": GOLDEN, "paper-rig": GOLDEN_DIR / "paper-rig" / "golden.json"}
# Every operator the full graph may hold: standard ONNX, no control flow, no custom domain.
FULL_GRAPH_OPS = {
    "Add", "Cast", "Concat", "Constant", "Cos", "Div", "Equal", "Erf", "Exp", "Floor", "Gather", "Gelu", "Gemm",
    "Greater", "Identity", "Less", "Log", "MatMul", "Max", "Min", "Mul", "Neg", "Pow", "ReduceSum", "Reshape",
    "Sigmoid", "Sin", "Slice", "Sqrt", "Sub", "Transpose", "Unsqueeze", "Where",
}  # fmt: skip


@pytest.fixture(scope="module")
def blob() -> bytes:
    return full_graph(bundled_model_bytes(), "bundled")


@pytest.fixture(scope="module")
def session(blob):
    return ort.InferenceSession(blob, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module", params=sorted(NAMED_GOLDEN))
def named_session(request):
    """(a bundled model's name, its full graph under ONNX Runtime)."""
    name = request.param
    return name, ort.InferenceSession(full_graph(bundled_model_bytes(name), name), providers=["CPUExecutionProvider"])


def _run(session, x: dict, rvec, tvec, mask=None) -> dict:
    n = len(x["points_2d"])
    feeds = {
        "points_2d": np.asarray(x["points_2d"], np.float64),
        "points_3d": np.asarray(x["points_3d"], np.float64),
        "mask": np.ones(n, bool) if mask is None else mask,
        "K_c": np.asarray(x["K_c"], np.float64),
        "image_size": np.asarray(x["image_size"], np.float64),
        "rvec": np.asarray(rvec, np.float64),
        "tvec": np.asarray(tvec, np.float64),
    }
    return dict(zip([o.name for o in session.get_outputs()], session.run(None, feeds)))


def test_the_graph_is_standard_onnx_with_the_documented_signature(blob, session):
    proto = onnx.load_from_string(blob)
    assert {n.op_type for n in proto.graph.node} <= FULL_GRAPH_OPS
    assert all(n.domain in ("", "ai.onnx") for n in proto.graph.node)
    assert [i.name for i in session.get_inputs()] == list(INPUTS)
    assert [o.name for o in session.get_outputs()] == list(OUTPUTS)
    assert any(p.key == "dimenet_model_spec" for p in proto.metadata_props)


def test_the_graph_equals_the_runtime_on_every_golden_frame(named_session):
    """Within PARITY_PX: the golden set's |Delta K| are below PARITY_DELTA_PX, where the bound is that
    constant, the one the Node.js runner holds the golden frames to."""
    name, session = named_session
    golden = json.loads(NAMED_GOLDEN[name].read_text())
    worst = 0.0
    for frame in golden["frames"]:
        x, want = frame["inputs"], frame["expected"]
        assert np.abs(want["delta_k"]).max() < PARITY_DELTA_PX, frame["name"]
        out = _run(session, x, want["rvec"], want["tvec"])
        for key in ("delta_k", "K", "sigma"):
            worst = max(worst, float(np.abs(out[key] - np.array(want[key])).max()))
    assert worst <= PARITY_PX, worst


def test_the_node_runner_holds_the_golden_frames_to_the_parity_bound():
    text = (ROOT / "export" / "node_runner" / "run.mjs").read_text()
    (value,) = re.findall(r"^const TOLERANCE_PX = ([0-9.e+-]+);$", text, re.MULTILINE)
    assert float(value) == PARITY_PX


@pytest.mark.parametrize("unit", [1e-6, 1e-3, 1e3, 1e8])
def test_a_scene_in_any_unit_gives_the_runtime_s_delta_k(named_session, unit):
    """Issue 48 #2: the data step's Hessian inverted with its diagonal scaled to 1, as the runtime's, so a
    scene in units of 1e-6 mm is no longer 5.5e-4 px off on this frame (up to 4e-2 px on other rig frames) for
    the any-scene model."""
    name, session = named_session
    x = json.loads(NAMED_GOLDEN[name].read_text())["frames"][0]["inputs"]
    p2, p3, K_c = np.array(x["points_2d"]), np.array(x["points_3d"]) * unit, np.array(x["K_c"])
    rvec, tvec = solve_pnp_start(p2, p3, K_c)
    rect = Rectifier.load(name, K_c=K_c, image_size=tuple(int(v) for v in x["image_size"]))
    net = rect.network(p2, p3, rvec, tvec)
    out = _run(session, {**x, "points_3d": p3}, rvec, tvec)
    for key in ("delta_k", "K", "sigma"):
        np.testing.assert_allclose(out[key], getattr(net, key), rtol=0, atol=parity_px(net.delta_k), err_msg=key)


def test_masked_points_may_hold_anything_and_change_nothing(named_session):
    """Issue 48 #3: a masked point that is NaN, inf, huge or at the camera centre gives what a masked copy
    of a real point gives, bit for bit (NaN on every output before)."""
    name, session = named_session
    frame = json.loads(NAMED_GOLDEN[name].read_text())["frames"][0]
    x, want = frame["inputs"], frame["expected"]
    rvec, tvec = np.array(want["rvec"]), np.array(want["tvec"])
    p2, p3 = np.array(x["points_2d"]), np.array(x["points_3d"])
    mask = np.r_[np.ones(len(p2), bool), False]

    def padded(point_2d, point_3d) -> dict:
        return _run(
            session, {**x, "points_2d": np.r_[p2, [point_2d]], "points_3d": np.r_[p3, [point_3d]]}, rvec, tvec, mask
        )

    reference = padded(p2[0], p3[0])
    np.testing.assert_allclose(reference["delta_k"], want["delta_k"], rtol=0, atol=PARITY_PX)
    centre = -cv2.Rodrigues(rvec)[0].T @ tvec
    for junk_2d, junk_3d in (
        ([np.nan, 1.0], [np.nan, 0.0, 0.0]),
        ([np.inf, -np.inf], [np.inf, 1.0, -np.inf]),
        ([1e300, 0.0], [0.0, 1e300, 0.0]),
        (p2[0], centre),
    ):
        out = padded(junk_2d, junk_3d)
        for key, value in reference.items():
            np.testing.assert_array_equal(out[key], value, err_msg=f"{junk_2d}, {junk_3d}: {key}")


def test_a_frame_without_a_point_gives_k_c_and_the_population_sigma(named_session):
    """N = 0, or every point masked: Delta K = 0, K = K_c and sigma the population's, a frame that keeps K_c
    (``Rectifier.population_K_cov``), for both models (the default gave a NaN sigma, any-scene NaN)."""
    name, session = named_session
    x = json.loads(NAMED_GOLDEN[name].read_text())["frames"][8]["inputs"]  # half resolution: user px != model px
    rect = Rectifier.load(name, K_c=np.array(x["K_c"]), image_size=tuple(int(v) for v in x["image_size"]))
    none = (np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, bool))
    masked = (x["points_2d"], x["points_3d"], np.zeros(len(x["points_2d"]), bool))
    for p2, p3, mask in (none, masked):
        out = _run(session, {**x, "points_2d": p2, "points_3d": p3}, [0.1, 0.2, 0.3], [1.0, 2.0, 500.0], mask)
        np.testing.assert_array_equal(out["delta_k"], np.zeros(4))
        np.testing.assert_array_equal(out["K"], np.array(x["K_c"]))
        np.testing.assert_allclose(out["sigma"], np.sqrt(rect.population_K_cov.diagonal()), rtol=1e-12)
        np.testing.assert_array_equal(out["features"], 0.0)


def test_a_mask_and_any_pose_equal_the_runtime_on_those_points(session):
    frame = golden_frames()[0]
    keep = np.zeros(len(frame.points_2d), bool)
    keep[::3] = True
    rvec, tvec = solve_pnp_start(frame.points_2d[keep], frame.points_3d[keep], frame.K_c)
    rect = Rectifier.load(K_c=frame.K_c, image_size=frame.image_size)
    net = rect.network(frame.points_2d[keep], frame.points_3d[keep], rvec, tvec)
    x = {"points_2d": frame.points_2d, "points_3d": frame.points_3d, "K_c": frame.K_c, "image_size": frame.image_size}
    out = _run(session, x, rvec, tvec, keep)
    np.testing.assert_allclose(out["delta_k"], net.delta_k, rtol=0, atol=parity_px(net.delta_k))
    np.testing.assert_allclose(out["sigma"], net.sigma, rtol=0, atol=PARITY_PX)
    np.testing.assert_allclose(out["features"], net.features, rtol=1e-6, atol=1e-9)
    tilted = _run(session, x, rvec + 0.01, tvec, keep)  # the pose is an input: another pose, another feature
    assert np.abs(tilted["delta_k"] - out["delta_k"]).max() > 1e-3


def test_the_committed_golden_inputs_are_what_the_simulator_gives_today():
    golden = json.loads(GOLDEN.read_text())
    frames = golden_frames()
    assert [f.name for f in frames] == [g["name"] for g in golden["frames"]]
    for frame, stored in zip(frames, golden["frames"]):  # equal but for the last bits, which vary between runs
        np.testing.assert_allclose(frame.points_2d, np.array(stored["inputs"]["points_2d"]), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(frame.K_c, np.array(stored["inputs"]["K_c"]), rtol=1e-12, atol=1e-9)


def test_models_the_graph_does_not_hold_are_refused_by_name(tmp_path):
    from helpers import DEVICE_MODEL

    with pytest.raises(ModelError, match="the full graph holds generic models"):
        full_graph(Path(DEVICE_MODEL).read_bytes(), "device.onnx")


def test_the_export_command_writes_the_full_graph_and_the_golden_set(tmp_path, capsys):
    from dimenet.runtime.cli.main import main

    out = tmp_path / "full.onnx"
    assert main(["export", "default", "--graph", "full", "--out", str(out)]) == 0
    assert "full graph" in capsys.readouterr().out
    assert [i.name for i in ort.InferenceSession(str(out)).get_inputs()] == list(INPUTS)
    assert main(["export", "default", "--golden", str(tmp_path / "golden")]) == 0
    written = json.loads((tmp_path / "golden" / "golden.json").read_text())
    # The committed set is this release's, but for the last bits, which vary between machines: the simulator's
    # points by ~1e-12 px (numpy's and libm's SIMD paths differ between CPUs), which a planar frame's
    # ill-conditioned pose amplifies to ~2e-6 px in Delta K (galaxy-s8-planar-1, on another host than the
    # set's). So the outputs are held to the set's parity bound, PARITY_PX, and 1e-8 of their size.
    assert_json_close(written, json.loads(GOLDEN.read_text()), rtol=1e-8, atol=PARITY_PX)
    for args, words in (
        (["export", "default", "--out", str(tmp_path / "m.onnx")], "--graph mlp exports a RUN_DIR"),
        (["export", "any-scene", "--out", str(tmp_path / "m.onnx")], "--graph mlp exports a RUN_DIR"),
        (["export", "paper-rig", "--out", str(tmp_path / "m.onnx")], "--graph mlp exports a RUN_DIR"),
        (["export", "default"], "give --out FILE.onnx (a model) or --golden DIR"),
        (["export", "default", "--out", str(out), "--golden", str(tmp_path)], "one of them"),
    ):
        assert main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err


def test_the_paper_rig_model_s_committed_golden_set_is_what_export_writes_today(tmp_path, capsys):
    from dimenet.runtime.cli.main import main

    assert main(["export", "paper-rig", "--golden", str(tmp_path)]) == 0
    assert "golden vectors of paper-rig" in capsys.readouterr().out
    written = json.loads((tmp_path / "golden.json").read_text())
    assert_json_close(written, json.loads(NAMED_GOLDEN["paper-rig"].read_text()), rtol=1e-8, atol=1e-6)


@pytest.mark.parametrize("moments", [False, True])
def test_a_gated_data_step_model_s_graph_equals_the_runtime(tmp_path, moments):
    """The data step in the graph (two unrolled 10 x 10 inverses), the moments and the gated head's
    nodes: a random generic model of that kind against ``Rectifier.network`` on golden frames, at ORT's
    full optimizations (its MatmulTransposeFusion once broke a transposed product by a vector here)."""
    pytest.importorskip("torch")
    import torch

    from dimenet.export.onnx_export import export_model
    from dimenet.runtime.rectify.features import FeatureSpec
    from dimenet.runtime.rectify.grid import Grid
    from dimenet.runtime.rectify.spec import GenericCamera, ModelSpec
    from dimenet.training.model import dime_net

    bounds = np.array([[-100.0, 100.0], [-100.0, 100.0], [-300.0, 300.0], [-300.0, 300.0]])
    spec = ModelSpec(
        features=FeatureSpec(grid=Grid(8, 6), depth_mm=1000.0, data_step=True, moments=moments),
        K_c=None,
        image_size=None,
        K_bounds=None,
        hidden=(16, 16),
        generic=GenericCamera(3000.0, bounds),
        head="gated_step",
    )
    torch.manual_seed(0)
    path = tmp_path / "gated.onnx"
    path.write_bytes(export_model(dime_net(spec.features, spec.hidden, spec.head).eval(), spec))
    session = ort.InferenceSession(full_graph(path.read_bytes(), "gated"), providers=["CPUExecutionProvider"])
    assert (
        {"Gemm", "Sigmoid", "Slice", "Neg"}
        <= {n.op_type for n in onnx.load_from_string(full_graph(path.read_bytes(), "gated")).graph.node}
        <= FULL_GRAPH_OPS | {"Gemm", "Sigmoid", "Slice", "Neg"}
    )
    worst = 0.0
    for frame in golden_frames()[::4]:
        rect = Rectifier.load(path, K_c=frame.K_c, image_size=frame.image_size)
        rvec, tvec = solve_pnp_start(frame.points_2d, frame.points_3d, frame.K_c)
        net = rect.network(frame.points_2d, frame.points_3d, rvec, tvec)
        x = {
            "points_2d": frame.points_2d,
            "points_3d": frame.points_3d,
            "K_c": frame.K_c,
            "image_size": frame.image_size,
        }
        out = _run(session, x, rvec, tvec)
        np.testing.assert_allclose(out["features"][0, -80:], net.features[0, -80:], rtol=1e-6, atol=1e-6)
        worst = max(
            worst, float(np.abs(out["delta_k"] - net.delta_k).max()) / parity_px(net.delta_k)
        )  # in parity bounds
    assert worst <= 1.0, worst
