"""Issue 20: export stamps the spec with ``weights_sha256`` (spec 1.4), the sha256 of the file's
bytes with that value set to 64 zeros, which the runtime checks without onnx; ``restamp_model``
gives an older file the stamp with its graph and weights untouched (how the bundled default
model was re-stamped). Needs torch and onnx (else skipped); a tiny 2x2-grid model keeps it fast.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
torch = pytest.importorskip("torch")

from helpers import DEVICE_MODEL

from dimenet.export.onnx_export import export_model, restamp_model, stamp_weights_sha256
from dimenet.runtime.assets import asset
from dimenet.runtime.errors import ModelError
from dimenet.runtime.geometry import k_matrix
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import DEFAULT_MODEL, load_onnx_model, onnx_model_from_bytes
from dimenet.runtime.rectify.spec import (
    METADATA_KEY,
    VERSION,
    WEIGHTS_SHA256_KEY,
    WEIGHTS_SHA256_PLACEHOLDER,
    ModelSpec,
)
from dimenet.runtime.rectify.uncertainty import Uncertainty
from dimenet.training.model import DimeNet


@pytest.fixture(scope="module")
def spec() -> ModelSpec:
    coef = np.zeros((4, 5))
    coef[:, 0] = np.log([1.0, 1.0, 3.0, 3.0])
    return ModelSpec(
        features=FeatureSpec(grid=Grid(2, 2)),
        K_c=k_matrix([3000.0, 3000.0, 2016.0, 1512.0]),
        image_size=(4032, 3024),
        K_bounds=np.array([[2900.0, 3100.0], [2900.0, 3100.0], [1900.0, 2100.0], [1400.0, 1600.0]]),
        hidden=(8, 8),
        provenance={"note": "tiny integrity test model"},
        uncertainty=Uncertainty(coef=coef, correlation=np.eye(4)),
    )


@pytest.fixture(scope="module")
def net(spec) -> DimeNet:
    torch.manual_seed(0)
    return DimeNet(spec.features.size, spec.hidden).eval()


@pytest.fixture(scope="module")
def blob(net, spec) -> bytes:
    return export_model(net, spec)


def _meta(blob: bytes) -> dict:
    proto = onnx.load_from_string(blob)
    return json.loads(next(p.value for p in proto.metadata_props if p.key == METADATA_KEY))


def _independent_digest(blob: bytes, digest: str) -> str:
    """The stamp rule, recomputed here: the digest's one occurrence set to 64 zeros, then sha256."""
    assert blob.count(digest.encode()) == 1
    return hashlib.sha256(blob.replace(digest.encode(), WEIGHTS_SHA256_PLACEHOLDER.encode())).hexdigest()


def test_export_writes_a_verifiable_weights_sha256(blob, spec):
    stored = _meta(blob)
    assert stored["version"] == VERSION == "1.11.0"
    digest = stored[WEIGHTS_SHA256_KEY]
    assert len(digest) == 64 and digest != WEIGHTS_SHA256_PLACEHOLDER
    assert _independent_digest(blob, digest) == digest
    onnx.checker.check_model(onnx.load_from_string(blob), full_check=True)  # same-length stamp: still valid
    model = onnx_model_from_bytes(blob, "tiny.onnx")
    assert model.spec.weights_sha256 == digest and model.sha256 == hashlib.sha256(blob).hexdigest()
    assert model.spec.to_dict() == spec.to_dict()  # the hash belongs to the file, not to the spec's content


def test_export_run_writes_the_stamp(tmp_path, net, spec, monkeypatch):
    from dimenet.export.onnx_export import export_run
    from dimenet.training.run_dir import write_run

    monkeypatch.setattr("dimenet.training.run_dir.curve_png", lambda history: b"")  # matplotlib: slow, not tested here
    run_dir = write_run(tmp_path / "run", net, spec, [{"epoch": 1, "train_mse_px2": 1.0, "val_e_px": 1.0}])
    out = export_run(run_dir, tmp_path / "model.onnx")
    written = out.read_bytes()
    assert _independent_digest(written, _meta(written)[WEIGHTS_SHA256_KEY]) == _meta(written)[WEIGHTS_SHA256_KEY]
    assert load_onnx_model(out).spec.weights_sha256 == _meta(written)[WEIGHTS_SHA256_KEY]


def test_a_changed_weight_in_an_exported_file_is_a_model_error(blob, tmp_path):
    proto = onnx.load_from_string(blob)
    weight = max(proto.graph.initializer, key=lambda t: len(t.raw_data))
    raw = bytes(weight.raw_data)
    values = onnx.numpy_helper.to_array(weight).copy()
    values.flat[3] = np.nextafter(values.flat[3], np.float32(np.inf))  # one ulp of one weight
    weight.CopyFrom(onnx.numpy_helper.from_array(values, weight.name))
    edited = tmp_path / "edited.onnx"
    edited.write_bytes(proto.SerializeToString())
    with pytest.raises(ModelError, match=r"edited\.onnx: the model file's bytes differ from the sha256 in its spec"):
        load_onnx_model(edited)
    flipped = bytearray(blob)
    flipped[blob.index(raw[:16]) + 5] ^= 0x10
    with pytest.raises(ModelError, match=r"^flipped: the model file's bytes differ from the sha256 in its spec"):
        onnx_model_from_bytes(bytes(flipped), "flipped")


def test_export_refuses_a_spec_the_runtime_would_refuse(net, spec):
    bad = replace(spec, K_bounds=np.array([[3100.0, 3200.0], [2900.0, 3100.0], [1900.0, 2100.0], [1400.0, 1600.0]]))
    with pytest.raises(ModelError, match=r"K_bounds of fx .* must contain K_c's fx"):
        export_model(net, bad)


def test_the_stamp_needs_exactly_one_placeholder():
    with pytest.raises(ModelError, match="placeholder weights_sha256 does not occur exactly once"):
        stamp_weights_sha256(b"no spec here")
    entry = b'"weights_sha256": "' + WEIGHTS_SHA256_PLACEHOLDER.encode() + b'"'
    with pytest.raises(ModelError, match="placeholder weights_sha256 does not occur exactly once"):
        stamp_weights_sha256(b"x" + entry + b"y" + entry)


def _as_spec_1_3(blob: bytes) -> bytes:
    proto = onnx.load_from_string(blob)
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    d = json.loads(entry.value)
    d["version"] = "1.3.0"
    del d[WEIGHTS_SHA256_KEY]
    d.pop("content_sha256", None)
    entry.value = json.dumps(d, indent=1, sort_keys=True)
    return proto.SerializeToString()


def test_restamp_gives_an_old_file_the_hash_and_keeps_graph_and_weights(blob):
    old = _as_spec_1_3(blob)
    assert onnx_model_from_bytes(old, "old").spec.weights_sha256 is None
    assert onnx_model_from_bytes(old, "old").spec.content_sha256 is None
    new = restamp_model(old, "old")
    a, b = onnx.load_from_string(old), onnx.load_from_string(new)
    assert a.graph.SerializeToString() == b.graph.SerializeToString()
    assert (a.ir_version, a.producer_name, a.producer_version, list(a.opset_import)) == (
        b.ir_version,
        b.producer_name,
        b.producer_version,
        list(b.opset_import),
    )
    assert new == blob  # the same bytes as exporting with the stamp in the first place
    features = np.random.default_rng(1).normal(size=(5, 20)).astype(np.float32)
    np.testing.assert_array_equal(
        onnx_model_from_bytes(new, "new").delta_k(features), onnx_model_from_bytes(old, "old").delta_k(features)
    )


def test_the_earlier_device_model_was_stamped_by_restamp_model():
    bundled = DEVICE_MODEL.read_bytes()
    assert _meta(bundled)["version"] == "1.4.0"
    assert restamp_model(_as_spec_1_3(bundled), "bundled 1.3") == restamp_model(bundled, "bundled")


def test_the_bundled_generic_model_is_as_export_stamps_it():
    bundled = asset(DEFAULT_MODEL).read_bytes()
    assert _meta(bundled)["version"] == "1.11.0" and "generic" in _meta(bundled)
    assert restamp_model(bundled, "bundled") == bundled  # idempotent, and the one implementation
