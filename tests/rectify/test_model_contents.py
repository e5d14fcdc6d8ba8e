"""Issue 33, "a model holds its own weights and loads in bounded time": a model file holds only
what `dimenet export` writes (rectify/onnx_graph.py), checked on its bytes before ONNX Runtime
makes a session, so external data, control flow, foreign operators, tensors whose data does not
match their shape and oversize files are a ModelError naming the file, never a model whose K
depends on another file, a hang or a traceback. Building the graphs needs onnx (skipped without)."""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest
from helpers import DEVICE_MODEL

from dimenet.runtime.errors import ModelError
from dimenet.runtime.rectify.model import load_onnx_model
from dimenet.runtime.rectify.onnx_graph import MAX_FIELDS, MAX_MODEL_BYTES, check_model_bytes
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.spec import METADATA_KEY, WEIGHTS_SHA256_KEY


def crafted(edit) -> bytes:
    """The device model, its spec without weights_sha256 (so only the edit differs from a model
    the runtime loads), its proto edited by ``edit(proto)``."""
    proto = _proto()
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    d = json.loads(entry.value)
    del d[WEIGHTS_SHA256_KEY]
    entry.value = json.dumps(d)
    edit(proto)
    return proto.SerializeToString()


def _tensor(name, dims, raw: bytes):
    from onnx import TensorProto

    t = TensorProto(name=name, data_type=TensorProto.FLOAT, raw_data=raw)
    t.dims.extend(dims)
    return t


def _external(tensor, location: str, length: int) -> None:
    from onnx import TensorProto

    tensor.ClearField("raw_data")
    tensor.data_location = TensorProto.EXTERNAL
    for key, value in (("location", location), ("offset", "0"), ("length", str(length))):
        entry = tensor.external_data.add()
        entry.key, entry.value = key, value


def external_weight(proto) -> None:
    """The (240, 256) weight moved to "weights.bin" in the process's current folder."""
    weight = next(t for t in proto.graph.initializer if list(t.dims) == [240, 256])
    _external(weight, "weights.bin", 240 * 256 * 4)


def external_passwd(proto) -> None:
    t = _tensor("unused", [4], b"")
    _external(t, "/etc/passwd", 16)
    proto.graph.initializer.append(t)


def huge_unused(proto) -> None:
    proto.graph.initializer.append(_tensor("unused", [100000, 100000], bytes(16)))


def segment(proto) -> None:
    t = _tensor("unused", [4], bytes(16))
    t.segment.begin, t.segment.end = 0, 2
    proto.graph.initializer.append(t)


def loop_of_2_60(proto) -> None:
    """The graph ends in a Loop of 2**60 trivial iterations (passes every static check before)."""
    from onnx import TensorProto, helper, numpy_helper

    graph = proto.graph
    graph.node[-1].output[0] = "pre"
    body = helper.make_graph(
        [helper.make_node("Identity", ["c"], ["c_out"]), helper.make_node("Identity", ["v"], ["v_out"])],
        "body",
        [
            helper.make_tensor_value_info("i", TensorProto.INT64, []),
            helper.make_tensor_value_info("c", TensorProto.BOOL, []),
            helper.make_tensor_value_info("v", TensorProto.FLOAT, None),
        ],
        [
            helper.make_tensor_value_info("c_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info("v_out", TensorProto.FLOAT, None),
        ],
    )
    graph.initializer.extend(
        [numpy_helper.from_array(np.array(2**60, np.int64), "M"), numpy_helper.from_array(np.array(True), "T")]
    )
    graph.node.append(helper.make_node("Loop", ["M", "T", "pre"], ["delta_k"], name="forever", body=body))


def tanh_for_erf(proto) -> None:
    for node in proto.graph.node:
        if node.op_type == "Erf":
            node.op_type = "Tanh"


def other_domain(proto) -> None:
    proto.graph.node[0].domain = "com.microsoft"


def sparse_initializer(proto) -> None:
    from onnx import helper, numpy_helper

    values, indices = numpy_helper.from_array(np.ones(1, np.float32), "v"), numpy_helper.from_array(np.zeros(1), "i")
    proto.graph.sparse_initializer.append(helper.make_sparse_tensor(values, indices, [4]))


def float64_constant(proto) -> None:
    from onnx import numpy_helper

    proto.graph.initializer.append(numpy_helper.from_array(np.zeros(4, np.float64), "doubles"))


def local_function(proto) -> None:
    from onnx import helper

    proto.functions.append(helper.make_function("custom", "Twice", ["x"], ["y"], [], [], []))


HOSTILE = [
    (external_weight, r"initializer '.*' keeps its values in an external file: a model file must hold its weights"),
    (external_passwd, r"initializer 'unused' keeps its values in an external file"),
    (huge_unused, r"initializer 'unused' declares shape \[100000, 100000\] \(10000000000 float32 values\) but holds"),
    (segment, r"initializer 'unused' is a segment of a tensor"),
    (loop_of_2_60, r"node \d+ \('forever'\) holds a subgraph: a DIME-Net graph has no control flow"),
    (tanh_for_erf, r"node \d+ \('/act/Erf'\) is the operator 'Tanh', which `dimenet export` never writes"),
    (other_domain, r"node 0 \('.*'\) is the operator 'com.microsoft:MatMul'"),
    (sparse_initializer, r"the graph has a sparse initializer: the exporter writes none"),
    (float64_constant, r"initializer 'doubles' has ONNX data type 11: the exporter writes float32"),
    (local_function, r"the model defines functions: the exporter writes none"),
]


@pytest.mark.parametrize(("edit", "message"), HOSTILE, ids=[edit.__name__ for edit, _ in HOSTILE])
def test_a_graph_holding_more_than_the_exporter_writes_is_refused_before_a_session(
    edit, message, tmp_path, monkeypatch
):
    path = tmp_path / "crafted.onnx"
    path.write_bytes(crafted(edit))
    (tmp_path / "weights.bin").write_bytes(np.ones(240 * 256, np.float32).tobytes())
    monkeypatch.chdir(tmp_path)  # where ONNX Runtime resolves a relative external location from bytes
    monkeypatch.setattr(ort, "InferenceSession", None)  # refused on the bytes: no session, no probe run
    with pytest.raises(ModelError, match=rf"^{tmp_path}/crafted\.onnx: {message}"):
        Rectifier.load(path)


def test_without_the_check_onnx_runtime_takes_a_weight_from_the_current_folder(tmp_path, monkeypatch):
    """Why external data is refused: from bytes, ONNX Runtime reads weights.bin of the cwd, so
    the same model bytes give another Delta K in another folder."""
    numpy_helper = pytest.importorskip("onnx.numpy_helper")  # the base install has no onnx: skip, not fail

    monkeypatch.chdir(tmp_path)
    weight = next(t for t in _proto().graph.initializer if list(t.dims) == [240, 256])
    features = np.random.default_rng(0).normal(size=(1, 240)).astype(np.float32) * 0.1
    outputs = []
    for factor in (1.0, 3.0):
        (tmp_path / "weights.bin").write_bytes((numpy_helper.to_array(weight) * factor).astype(np.float32).tobytes())
        session = ort.InferenceSession(crafted(external_weight), providers=["CPUExecutionProvider"])
        outputs.append(session.run(None, {"features": features})[0])
    assert not np.allclose(*outputs)
    with pytest.raises(ModelError, match="keeps its values in an external file"):
        load_onnx_model(_written(tmp_path, crafted(external_weight)))


def _proto():
    onnx = pytest.importorskip("onnx")
    return onnx.load_from_string(DEVICE_MODEL.read_bytes())


def _written(folder, blob):
    path = folder / "m.onnx"
    path.write_bytes(blob)
    return path


def test_the_bundled_and_device_models_hold_only_what_the_exporter_writes():
    from dimenet.runtime.assets import asset
    from dimenet.runtime.rectify.model import BUNDLED_MODELS

    for blob in (*(asset(f).read_bytes() for f in sorted(set(BUNDLED_MODELS.values()))), DEVICE_MODEL.read_bytes()):
        check_model_bytes(blob, "model")  # no error


def test_a_model_file_past_the_cap_is_refused_reading_at_most_the_cap(tmp_path):
    big = tmp_path / "big.onnx"
    with big.open("wb") as f:
        f.truncate(8 << 30)  # 8 GiB, sparse: a reader without the cap reads it all
    with pytest.raises(ModelError, match=rf"big\.onnx: larger than {MAX_MODEL_BYTES} bytes, too large for a DIME-Net"):
        Rectifier.load(big)
    with pytest.raises(ModelError, match=rf"^bytes: larger than {MAX_MODEL_BYTES} bytes"):
        check_model_bytes(bytes(MAX_MODEL_BYTES + 1), "bytes")


def test_bytes_that_are_no_protobuf_are_not_a_loadable_model():
    for blob in (b"\x0a\xff\xff\xff\xff\x0f", b"\x0b\x00", b"\x80" * 11, b"\x00\x01"):
        with pytest.raises(ModelError, match=r"^junk: not a loadable ONNX model \(malformed protobuf: "):
            check_model_bytes(blob, "junk")


def test_a_file_of_countless_tiny_fields_is_refused_within_the_field_budget():
    import time

    blob = b"\x08\x00" * (MAX_MODEL_BYTES // 2)  # 33 million fields: 11 s to walk them all
    start = time.monotonic()
    with pytest.raises(ModelError, match=rf"^tiny: more than {MAX_FIELDS} protobuf fields"):
        check_model_bytes(blob, "tiny")
    assert time.monotonic() - start < 2.0


def test_a_name_with_control_characters_stays_on_one_line(tmp_path):
    def renamed(proto):
        tanh_for_erf(proto)
        next(n for n in proto.graph.node if n.op_type == "Tanh").name = "evil\n\x1b[2J" + "x" * 500

    with pytest.raises(ModelError) as refused:
        check_model_bytes(crafted(renamed), "m.onnx")
    message = str(refused.value)
    assert "\n" not in message and "\x1b" not in message and "'evil\\n\\x1b[2J" in message and len(message) < 300
