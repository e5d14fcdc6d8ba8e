"""`dimenet export --format ort` (ORT Mobile's format), the content hash (spec 1.9, rectify.integrity) and
the .ort file's own hash (rectify.ort_format.ORT_SHA256_KEY): the converted file loads in the runtime with
its spec, weights and graph checked, gives the ONNX file's Delta K to float32 rounding, and a changed weight,
a changed operator, a file without either hash or a foreign operator is refused."""

from __future__ import annotations

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")

from dimenet.export.onnx_export import ort_format_bytes  # noqa: E402
from dimenet.runtime.errors import ModelError  # noqa: E402
from dimenet.runtime.rectify.integrity import content_sha256, zeroed_spec_text  # noqa: E402
from dimenet.runtime.rectify.model import bundled_model_bytes, onnx_model_from_bytes  # noqa: E402
from dimenet.runtime.rectify.onnx_graph import check_model_bytes  # noqa: E402
from dimenet.runtime.rectify.ort_format import ORT_SHA256_KEY, check_ort_bytes, is_ort_format  # noqa: E402
from dimenet.runtime.rectify.spec import METADATA_KEY  # noqa: E402


@pytest.fixture(scope="module")
def onnx_blob() -> bytes:
    return bundled_model_bytes()


@pytest.fixture(scope="module")
def ort_blob(onnx_blob) -> bytes:
    return ort_format_bytes(onnx_blob, "bundled")


def test_the_ort_file_loads_with_the_same_spec_content_and_delta_k(onnx_blob, ort_blob):
    assert is_ort_format(ort_blob) and not is_ort_format(onnx_blob)
    a, b = onnx_model_from_bytes(onnx_blob, "onnx"), onnx_model_from_bytes(ort_blob, "ort")
    assert b.spec.to_json(content_sha256=b.spec.content_sha256) == a.spec.to_json(content_sha256=a.spec.content_sha256)
    assert a.spec.content_sha256 is not None
    features = np.random.default_rng(2).normal(size=(32, a.spec.features.size)).astype(np.float32)
    assert np.abs(b.delta_k(features) - a.delta_k(features)).max() < 1e-3  # float32 kernels, no fusion
    onnx_tensors = {t.name: t for t in check_model_bytes(onnx_blob, "onnx")}
    ort_tensors = {t.name: t for t in check_ort_bytes(ort_blob, "ort")}
    assert onnx_tensors == ort_tensors  # the Constant nodes became initializers of the same name and values


def test_the_content_hash_is_the_documented_one_and_catches_one_changed_weight(onnx_blob, ort_blob):
    proto = onnx.load_from_string(onnx_blob)
    text = next(p.value for p in proto.metadata_props if p.key == METADATA_KEY)
    assert '"content_sha256": "' + "0" * 64 + '"' in zeroed_spec_text(text)
    tensors = check_model_bytes(onnx_blob, "onnx")
    assert content_sha256(text, tensors) == onnx_model_from_bytes(onnx_blob, "x").spec.content_sha256
    biggest = max(tensors, key=lambda t: len(t.data))
    where = ort_blob.find(biggest.data[:64])
    assert where > 0
    changed = bytearray(ort_blob)
    changed[where + 8] ^= 1  # one bit of one weight
    with pytest.raises(ModelError, match=r"changed\.ort: the model's spec and weights differ from the content_sha256"):
        onnx_model_from_bytes(bytes(changed), "changed.ort")


def test_an_ort_file_without_either_hash_or_with_a_foreign_operator_is_refused(onnx_blob, tmp_path):
    import onnxruntime as ort

    proto = onnx.load_from_string(onnx_blob)
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    entry.value = entry.value.replace('"content_sha256"', '"note"')
    relu = onnx.helper.make_node("Relu", [proto.graph.node[-1].output[0]], ["relu_out"])
    for blob, message in (
        # converted as the 0.6 releases did: the spec's content_sha256, no hash of the graph
        (onnx_blob, rf"unstamped\.ort: an ORT-format model needs its {ORT_SHA256_KEY}, the hash that covers its graph"),
        (proto.SerializeToString(), r"old\.ort: an ORT-format model needs the content_sha256 of spec >= 1\.9"),
        (None, r"foreign\.ort: node \d+ .* is the operator 'Relu', which `dimenet export` never writes"),
    ):
        if blob is None:
            proto.graph.node.append(relu)
            proto.graph.output[0].name = "relu_out"
            blob = proto.SerializeToString()
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
        options.add_session_config_entry("session.save_model_format", "ORT")
        options.optimized_model_filepath = str(tmp_path / "converted.ort")
        ort.InferenceSession(blob, options, providers=["CPUExecutionProvider"])
        name = message.split("\\.")[0] + ".ort"
        with pytest.raises(ModelError, match=message):
            onnx_model_from_bytes((tmp_path / "converted.ort").read_bytes(), name)


def _changed_operator(blob: bytes, old: bytes, new: bytes) -> bytes:
    """The bytes with the first node operator type ``old`` spelled ``new`` (same length): in an ORT-format
    file a flatbuffer string (uint32 length, the name, a NUL), in an ONNX file a node's field 4."""
    if is_ort_format(blob):
        start = blob.index(len(old).to_bytes(4, "little") + old + b"\0") + 4
    else:
        start = blob.index(b"\x22" + bytes([len(old)]) + old) + 2
    return blob[:start] + new + blob[start + len(old) :]


def test_an_ort_file_with_one_div_made_a_mul_is_refused():
    # issue 48, #4: the content hash leaves out the graph, so this file loaded and gave a K 0.53 px off
    onnx_blob = bundled_model_bytes("any-scene")
    ort_blob = ort_format_bytes(onnx_blob, "any-scene")
    loaded = onnx_model_from_bytes(ort_blob, "any-scene.ort")  # the untampered conversion loads
    tampered = _changed_operator(ort_blob, b"Div", b"Mul")
    assert check_ort_bytes(tampered, "x") == check_ort_bytes(ort_blob, "x")  # the tensors and spec are untouched
    with pytest.raises(
        ModelError,
        match=rf"^mul\.ort: the ORT-format file's bytes \(graph, weights and spec\) differ from its {ORT_SHA256_KEY}",
    ):
        onnx_model_from_bytes(tampered, "mul.ort")
    assert len(loaded.sha256) == 64 and loaded.sha256 != onnx_model_from_bytes(onnx_blob, "x").sha256
    # the ONNX file has no such hole: its weights_sha256 covers every byte, the graph too
    with pytest.raises(ModelError, match=r"^mul\.onnx: the model file's bytes differ from the sha256 in its spec"):
        onnx_model_from_bytes(_changed_operator(onnx_blob, b"Div", b"Mul"), "mul.onnx")


def test_the_ort_hash_is_the_sha256_of_the_file_with_its_digits_zeroed(ort_blob):
    import hashlib

    digest = onnx_model_from_bytes(ort_blob, "x").session.get_modelmeta().custom_metadata_map[ORT_SHA256_KEY]
    assert ort_blob.count(digest.encode()) == 1
    assert hashlib.sha256(ort_blob.replace(digest.encode(), b"0" * 64)).hexdigest() == digest
    other = ("1" if digest[0] == "0" else "0") + digest[1:]
    with pytest.raises(
        ModelError, match=rf"^digit\.ort: the ORT-format file's bytes .* differ from its {ORT_SHA256_KEY}"
    ):
        onnx_model_from_bytes(ort_blob.replace(digest.encode(), other.encode()), "digit.ort")


def test_a_truncated_ort_file_is_one_model_error(ort_blob):
    for cut in (8, 100, len(ort_blob) // 2):
        with pytest.raises(ModelError, match=r"cut\.ort: "):
            onnx_model_from_bytes(ort_blob[:cut], "cut.ort")


def test_export_format_ort_from_the_command_line(tmp_path, capsys):
    from dimenet.runtime.cli.main import main

    out = tmp_path / "dimenet.ort"
    assert main(["export", "default", "--format", "ort", "--out", str(out)]) == 0
    assert "ort" in capsys.readouterr().out and is_ort_format(out.read_bytes())
    assert main(["rectify", "--example", "--model", str(out), "--json"]) == 0
    assert main(["export", "default", "--graph", "full", "--format", "ort", "--out", str(tmp_path / "f.ort")]) == 2
    assert "--format ort converts a model (--graph mlp)" in capsys.readouterr().err
