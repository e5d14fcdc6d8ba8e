"""Initial weights for fine-tuning (training/init_weights.py): from an exported ONNX file, a
RUN_DIR and the bundled default model, and every bad source refused by name. No training."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")  # the base-only install has no torch: skip, not fail
onnx = pytest.importorskip("onnx")

from helpers import model_spec, random_torch_model
from onnx import helper, numpy_helper

from dimenet.export.onnx_export import export_model
from dimenet.export.opset import DEFAULT_OPSET, MAX_OPSET, MIN_OPSET
from dimenet.runtime.errors import ModelError
from dimenet.runtime.rectify import model as model_module
from dimenet.runtime.rectify.model import load_model, load_onnx_model
from dimenet.runtime.rectify.spec import METADATA_KEY
from dimenet.runtime.sim.simulator import simulate
from dimenet.training.init_weights import InitialWeights, initial_weights
from dimenet.training.model import DimeNet, dime_net
from dimenet.training.run_dir import WEIGHTS, write_run

KEYS = ["fc1.weight", "fc2.weight", "fc3.weight"]


@pytest.fixture(scope="module")
def spec():
    return model_spec(simulate("galaxy-s8", seed=0))


@pytest.fixture(scope="module")
def torch_model(spec):
    return random_torch_model(spec, seed=11)


@pytest.fixture(scope="module")
def exported(tmp_path_factory, torch_model, spec):
    path = tmp_path_factory.mktemp("export") / "model.onnx"
    path.write_bytes(export_model(torch_model, spec))
    return path


def _features(spec, frames=32, seed=5):
    return np.random.default_rng(seed).normal(size=(frames, spec.features.size)).astype(np.float32)


def _outputs(state_dict, spec, features):
    model = dime_net(spec.features, spec.hidden, spec.head)
    model.load_state_dict(state_dict)  # strict: exactly the head's DimeNet keys and shapes
    with torch.no_grad():
        return model.eval()(torch.from_numpy(features)).numpy()


def _torch_outputs(model, features):
    with torch.no_grad():
        return model(torch.from_numpy(features)).numpy()


def _assert_same_weights(weights: InitialWeights, model: DimeNet):
    assert list(weights.state_dict) == KEYS
    for key, value in model.state_dict().items():
        got = weights.state_dict[key]
        assert got.dtype == torch.float32 and got.shape == value.shape and got.is_contiguous()
        assert torch.equal(got, value), key


@pytest.mark.parametrize("opset", sorted({MIN_OPSET, DEFAULT_OPSET, MAX_OPSET}))
def test_an_exported_model_gives_back_torchs_weights_and_outputs(tmp_path, torch_model, spec, opset):
    path = tmp_path / f"opset{opset}.onnx"
    path.write_bytes(export_model(torch_model, spec, opset=opset))
    weights = initial_weights(str(path))
    assert weights.source == str(path) and weights.spec.to_dict() == spec.to_dict()
    _assert_same_weights(weights, torch_model)  # the output scale stays out of fc3, exactly
    features = _features(spec)
    expected = _torch_outputs(torch_model, features)
    got = _outputs(weights.state_dict, spec, features)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())


def test_a_run_dir_gives_back_its_weights_and_spec(tmp_path, torch_model, spec):
    history = [{"epoch": 1, "train_mse_px2": 4.0, "val_e_px": 2.0}]
    run_dir = write_run(tmp_path / "run", torch_model, spec, history)
    weights = initial_weights(str(run_dir))
    assert weights.source == str(run_dir) and weights.spec.to_dict() == spec.to_dict()
    _assert_same_weights(weights, torch_model)
    features = _features(spec)
    expected = _torch_outputs(torch_model, features)
    np.testing.assert_allclose(
        _outputs(weights.state_dict, spec, features), expected, rtol=0, atol=1e-5 * np.abs(expected).max()
    )
    # the state dict is its own: changing it leaves the next read alone
    weights.state_dict["fc1.weight"].zero_()
    assert torch.equal(initial_weights(str(run_dir)).state_dict["fc1.weight"], torch_model.fc1.weight)


@pytest.mark.parametrize("name", ["default", "paper-rig"])
def test_each_bundled_model_reproduces_onnx_runtime(spec, name):
    weights = initial_weights(name)
    bundled = load_model(name)
    assert weights.source == name and weights.spec.to_dict() == bundled.spec.to_dict()
    features = _features(bundled.spec, frames=64)
    got = _outputs(weights.state_dict, weights.spec, features)
    np.testing.assert_allclose(got, bundled.delta_k(features), rtol=1e-6, atol=1e-4)
    zeros = np.zeros((2, weights.spec.features.size), np.float32)
    assert np.all(_outputs(weights.state_dict, weights.spec, zeros) == 0.0)


# -- edited graphs: re-embedded with a spec without weights_sha256, so only the edit differs --


def _edited(src, dst, edit, spec_edit=None):
    proto = onnx.load(str(src))
    edit(proto.graph)
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    d = json.loads(entry.value)
    del d["weights_sha256"], d["content_sha256"]  # an edited graph: no stamp to check
    if spec_edit is not None:
        spec_edit(d)
    entry.value = json.dumps(d)
    dst.write_bytes(proto.SerializeToString())
    return dst


def _last_matrix(graph):
    node = [n for n in graph.node if n.op_type == "MatMul"][-1]
    return next(i for i in graph.initializer if i.name == node.input[1])


def _fold_scale(graph):
    """The exporter's graph with the final Mul by 10 folded into the last matrix."""
    init = _last_matrix(graph)
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * 10.0, init.name))
    mul = graph.node[-1]
    assert mul.op_type == "Mul" and mul.output[0] == "delta_k"
    last = next(n for n in graph.node if mul.input[0] in n.output)
    last.output[0] = "delta_k"
    graph.node.remove(mul)


def _as_gemm(graph):
    """Every MatMul as a bias-free Gemm of the (out, in) weight with transB = 1."""
    for k, node in enumerate(list(graph.node)):
        if node.op_type == "MatMul":
            init = next(i for i in graph.initializer if i.name == node.input[1])
            init.CopyFrom(numpy_helper.from_array(np.ascontiguousarray(numpy_helper.to_array(init).T), init.name))
            gemm = helper.make_node("Gemm", list(node.input), list(node.output), name=node.name, transB=1)
            graph.node.remove(node)
            graph.node.insert(k, gemm)


def test_the_scale_folded_into_the_last_matrix_reads_the_same(exported, tmp_path, torch_model, spec):
    path = _edited(exported, tmp_path / "edited.onnx", _fold_scale)
    features = _features(spec)
    np.testing.assert_allclose(
        load_onnx_model(path).delta_k(features), _torch_outputs(torch_model, features), rtol=1e-5, atol=1e-3
    )
    weights = initial_weights(str(path))
    for key, value in torch_model.state_dict().items():
        np.testing.assert_allclose(weights.state_dict[key].numpy(), value.numpy(), rtol=1e-6, atol=0)


def _add_bias(graph):
    first = graph.node[0]
    assert first.op_type == "MatMul"
    out = first.output[0]
    first.output[0] = "pre_bias"
    graph.initializer.append(numpy_helper.from_array(np.full(256, 0.1, np.float32), "fc1.bias"))
    graph.node.insert(1, helper.make_node("Add", ["pre_bias", "fc1.bias"], [out], name="bias_add"))


def _add_after_scale(graph):
    graph.node[-1].output[0] = "scaled"
    graph.node.append(helper.make_node("Add", ["scaled", "/Constant_output_0"], ["delta_k"], name="shift"))


def _tanh_for_erf(graph):
    for node in graph.node:
        if node.op_type == "Erf":
            node.op_type = "Tanh"


def _per_output_scale(graph):
    mul = graph.node[-1]
    graph.initializer.append(numpy_helper.from_array(np.zeros((1, 4), np.float32), "per_output"))
    mul.input[1] = "per_output"


def _weight_through_identity(graph):
    """The first MatMul multiplies by Identity(weight), a computed value, not the constant."""
    first = graph.node[0]
    graph.node.insert(0, helper.make_node("Identity", [first.input[1]], ["fc1_copy"], name="copy"))
    first.input[1] = "fc1_copy"


@pytest.mark.parametrize(
    ("edit", "spec_edit", "message"),
    [
        (_add_bias, None, r"Add node 'bias_add' reads the constant 'fc1.bias' of shape \[256\]: .* no biases"),
        (_as_gemm, None, r"Gemm node .* reads the constant .* only as the weights of its three MatMuls"),
        (_add_after_scale, None, r"after its last weight matrix the graph has the Add node 'shift'"),
        (_per_output_scale, None, r"Mul node .* reads the constant 'per_output' of shape \[1, 4\]"),
        (lambda g: None, lambda d: d.update(hidden=[256, 64]), r"3 matrices of \(out, in\) shapes .* needs 3 of"),
        (lambda g: None, lambda d: d.update(hidden=[256, 128, 4]), r"its spec has 3 hidden layers"),
    ],
)
def test_graphs_that_are_not_the_spec_s_mlp_are_refused_by_name(exported, tmp_path, edit, spec_edit, message):
    path = _edited(exported, tmp_path / "bad.onnx", edit, spec_edit)
    load_onnx_model(path)  # the runtime would load it: only the weights' reader refuses it
    with pytest.raises(ModelError, match=rf"bad\.onnx: .*{message}"):
        initial_weights(str(path))


@pytest.mark.parametrize(("edit", "op"), [(_weight_through_identity, "Identity"), (_tanh_for_erf, "Tanh")])
def test_operators_the_exporter_never_writes_are_refused_by_the_runtime_s_loader_first(exported, tmp_path, edit, op):
    path = _edited(exported, tmp_path / "other.onnx", edit)
    message = rf"other\.onnx: node \d+ \('.*'\) is the operator '{op}', which `dimenet export` never writes"
    with pytest.raises(ModelError, match=message):
        load_onnx_model(path)
    with pytest.raises(ModelError, match=message):
        initial_weights(str(path))


def _unused_initializer(graph):
    """An initializer no node reads, declaring (100000, 100000) float32 with 16 bytes of data."""
    t = onnx.TensorProto(name="unused", data_type=onnx.TensorProto.FLOAT, raw_data=bytes(16))
    t.dims.extend([100000, 100000])
    graph.initializer.append(t)


def _external_passwd(graph):
    t = onnx.TensorProto(name="passwd", data_type=onnx.TensorProto.FLOAT, data_location=onnx.TensorProto.EXTERNAL)
    t.dims.append(4)
    for key, value in (("location", "/etc/passwd"), ("offset", "0"), ("length", "16")):
        entry = t.external_data.add()
        entry.key, entry.value = key, value
    graph.initializer.append(t)


def _segment(graph):
    t = numpy_helper.from_array(np.zeros(4, np.float32), "part")
    t.segment.begin, t.segment.end = 0, 2
    graph.initializer.append(t)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (_unused_initializer, r"initializer 'unused' declares shape \[100000, 100000\] .* but holds 16 bytes"),
        (_external_passwd, r"initializer 'passwd' keeps its values in an external file"),
        (_segment, r"initializer 'part' is a segment of a tensor"),
    ],
)
def test_init_from_a_crafted_file_is_one_line_not_a_traceback(exported, tmp_path, capsys, edit, message):
    """Issue 33: files the runtime loaded and the onnx package then failed on (reshape, absolute
    external location, segments) are refused by the runtime's checked loader, `--init` included."""
    from dimenet.runtime.cli.main import main
    from dimenet.runtime.formats.dataset import write_dataset

    path = _edited(exported, tmp_path / "crafted.onnx", edit)
    with pytest.raises(ModelError, match=rf"crafted\.onnx: {message}"):
        initial_weights(str(path))
    data = tmp_path / "s8.npz"
    write_dataset(simulate("galaxy-s8", seed=0), data)
    assert main(["train", str(data), "--init", str(path), "--epochs", "1", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "crafted.onnx: " in err
    assert not (tmp_path / "run").exists()


def test_missing_foreign_and_corrupt_sources_are_refused_by_name(exported, tmp_path):
    with pytest.raises(ModelError, match=r"nowhere\.onnx: no such model file or RUN_DIR"):
        initial_weights(str(tmp_path / "nowhere.onnx"))
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x08\x07" + bytes(range(256)) * 4)
    with pytest.raises(ModelError, match=r"junk\.onnx: not a loadable ONNX model"):
        initial_weights(str(junk))
    foreign = tmp_path / "foreign.onnx"
    proto = onnx.load(str(exported))
    proto.ClearField("metadata_props")
    foreign.write_bytes(proto.SerializeToString())
    with pytest.raises(ModelError, match=rf"foreign\.onnx: no '{METADATA_KEY}'"):
        initial_weights(str(foreign))
    flipped = tmp_path / "flipped.onnx"
    blob = bytearray(exported.read_bytes())
    blob[len(blob) // 3] ^= 0x01  # one weight bit: the weights_sha256 catches it
    flipped.write_bytes(bytes(blob))
    with pytest.raises(ModelError, match=r"flipped\.onnx: "):
        initial_weights(str(flipped))


def test_broken_run_dirs_are_refused_by_name(tmp_path, torch_model, spec):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ModelError, match=r"empty/spec\.json: no model spec file"):
        initial_weights(str(empty))
    run_dir = write_run(tmp_path / "run", torch_model, spec, [{"epoch": 1, "train_mse_px2": 4.0, "val_e_px": 2.0}])
    (run_dir / WEIGHTS).write_bytes(b"not safetensors")
    with pytest.raises(ModelError, match=rf"run/{WEIGHTS}: unreadable or mismatched weights"):
        initial_weights(str(run_dir))


def test_a_trimmed_installation_without_the_default_model_is_refused(tmp_path, monkeypatch):
    monkeypatch.setitem(model_module.BUNDLED_MODELS, "default", "absent_model.onnx")
    with pytest.raises(ModelError, match=r"this installation has no bundled default model"):
        initial_weights("default")
