"""Export of the MLP to ONNX (`dimenet export`) and the runtime's ONNX model loader.

``model_spec`` and ``random_torch_model`` (helpers.py): a random-init DimeNet exported to ONNX
(needs torch and onnx, else the test is skipped).
"""

from __future__ import annotations

import json
import os
from dataclasses import replace

import numpy as np
import pytest
from helpers import model_spec, random_torch_model

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import ModelError
from dimenet.runtime.evaluation.predictor import load_predictor
from dimenet.runtime.rectify.features import grid_features
from dimenet.runtime.rectify.model import INPUT_NAME, OUTPUT_NAME, load_onnx_model
from dimenet.runtime.rectify.spec import FORMAT, METADATA_KEY, ModelSpec
from dimenet.runtime.sim.simulator import simulate


@pytest.fixture(scope="module")
def s8_dataset():
    return simulate("galaxy-s8", seed=0)


@pytest.fixture(scope="module")
def spec(s8_dataset):
    return model_spec(s8_dataset)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, spec):
    pytest.importorskip("onnx")
    from dimenet.training.run_dir import write_run

    history = [{"epoch": 1, "train_mse_px2": 4.0, "val_e_px": 2.0}]
    return write_run(tmp_path_factory.mktemp("run"), random_torch_model(spec, seed=3), spec, history)


@pytest.fixture(scope="module")
def exported(run_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "model.onnx"
    assert main(["export", str(run_dir), "--out", str(out)]) == 0
    return out


def _edited(src, dst, edit):
    """Copy an ONNX file with ``edit(proto)`` applied."""
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(src))
    edit(proto)
    dst.write_bytes(proto.SerializeToString())
    return dst


def test_export_is_a_checked_small_graph_with_the_spec(exported, spec):
    import onnx

    proto = onnx.load(str(exported))
    onnx.checker.check_model(proto, full_check=True)
    (inp,), (out,) = proto.graph.input, proto.graph.output
    assert (inp.name, out.name) == (INPUT_NAME, OUTPUT_NAME)
    assert [d.dim_param or d.dim_value for d in inp.type.tensor_type.shape.dim] == ["batch", spec.features.size]
    assert [d.dim_param or d.dim_value for d in out.type.tensor_type.shape.dim] == ["batch", 4]
    assert {n.op_type for n in proto.graph.node} <= {"MatMul", "Div", "Erf", "Add", "Mul", "Constant"}
    meta = {p.key: p.value for p in proto.metadata_props}
    stored = json.loads(meta[METADATA_KEY])
    assert stored["format"] == FORMAT and stored["version"].startswith("1.")
    assert ModelSpec.from_json(meta[METADATA_KEY]).to_dict() == spec.to_dict()
    assert os.path.getsize(exported) < 500_000


def test_onnx_matches_torch_on_every_simulated_test_frame(exported, run_dir, s8_dataset):
    import torch

    from dimenet.training.run_dir import load_run

    model, spec = load_run(run_dir)
    test = s8_dataset.select(s8_dataset.frames_in("test"))
    feats = grid_features(
        test.points_2d, test.points_3d, test.infer_mask, spec.K_c, spec.image_size, spec.features
    ).astype(np.float32)
    onnx_model = load_onnx_model(exported)
    with torch.no_grad():
        expected = model(torch.from_numpy(feats)).numpy()
    assert np.abs(onnx_model.delta_k(feats) - expected).max() <= 1e-3
    zero = onnx_model.delta_k(np.zeros((3, spec.features.size), np.float32))
    assert zero.shape == (3, 4) and np.all(zero == 0.0)
    # the `onnx` predictor entry point gives the same K as the torch RUN_DIR backend
    np.testing.assert_allclose(
        load_predictor(exported).predict_k(test), load_predictor(run_dir).predict_k(test), atol=1e-3
    )


def test_foreign_corrupt_and_future_models_are_refused_by_name(exported, tmp_path):
    def set_version(proto):
        entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
        d = json.loads(entry.value)
        d["version"] = "2.0.0"
        entry.value = json.dumps(d)

    future = _edited(exported, tmp_path / "future.onnx", set_version)
    with pytest.raises(ModelError, match=r"future\.onnx.*version '2\.0\.0' is not supported"):
        load_onnx_model(future)
    foreign = _edited(exported, tmp_path / "foreign.onnx", lambda proto: proto.ClearField("metadata_props"))
    with pytest.raises(ModelError, match=rf"foreign\.onnx.*no '{METADATA_KEY}'"):
        load_onnx_model(foreign)

    def other_grid(proto):
        entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
        d = json.loads(entry.value)
        d["features"]["grid"] = "4x3"
        entry.value = json.dumps(d)

    mismatched = _edited(exported, tmp_path / "mismatched.onnx", other_grid)
    with pytest.raises(ModelError, match=r"mismatched\.onnx.*\[batch, 60\]"):
        load_onnx_model(mismatched)


def test_corrupt_or_missing_files_are_model_errors(tmp_path):
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model at all")
    with pytest.raises(ModelError, match="garbage.onnx: not a loadable ONNX model"):
        load_onnx_model(garbage)
    with pytest.raises(ModelError, match="no such model file"):
        load_onnx_model(tmp_path / "absent.onnx")
    with pytest.raises(ModelError, match="a folder, the runtime needs a .onnx file"):
        load_onnx_model(tmp_path)


def test_truncated_file_is_a_model_error(exported, tmp_path):
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(exported.read_bytes()[:1000])
    with pytest.raises(ModelError, match="truncated.onnx: not a loadable ONNX model"):
        load_onnx_model(truncated)


def test_failed_export_leaves_the_previous_file_intact(exported, run_dir, tmp_path, monkeypatch):
    from dimenet.export.onnx_export import export_run
    from dimenet.training.run_dir import WEIGHTS

    out = tmp_path / "model.onnx"
    out.write_bytes(exported.read_bytes())
    before = out.read_bytes()
    broken = tmp_path / "broken_run"
    broken.mkdir()
    for name in os.listdir(run_dir):
        (broken / name).write_bytes((run_dir / name).read_bytes())
    (broken / WEIGHTS).write_bytes(b"corrupt")
    with pytest.raises(ModelError, match="weights"):
        export_run(broken, out)
    assert out.read_bytes() == before
    assert main(["export", str(run_dir), "--out", str(out), "--opset", "7"]) == 2
    assert out.read_bytes() == before

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("dimenet.runtime.formats.atomic.os.fsync", disk_full)
    with pytest.raises(OSError, match="No space"):
        export_run(run_dir, out)
    assert out.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["broken_run", "model.onnx"]


def test_every_opset_the_exporter_offers_writes_only_the_runtime_s_operators(spec):
    """rectify.onnx_graph.EXPORTED_OPS is the exporter's operator set: each opset's export (the paper's
    MLP and the gated step head) holds operators of it only, and the runtime loads it."""
    onnx = pytest.importorskip("onnx")
    from dimenet.export.commands import MAX_OPSET, MIN_OPSET
    from dimenet.export.onnx_export import export_model
    from dimenet.runtime.rectify.model import onnx_model_from_bytes
    from dimenet.runtime.rectify.onnx_graph import EXPORTED_OPS, ONNX_DOMAINS
    from dimenet.training.model import dime_net

    gated_spec = replace(spec, features=replace(spec.features, data_step=True), head="gated_step")
    gated = dime_net(gated_spec.features, gated_spec.hidden, gated_spec.head).eval()
    models = ((random_torch_model(spec, seed=3), spec), (gated, gated_spec))
    used = set()
    for opset in range(MIN_OPSET, MAX_OPSET + 1):
        for model, its_spec in models:
            blob = export_model(model, its_spec, opset=opset)
            nodes = onnx.load_from_string(blob).graph.node
            assert {n.domain for n in nodes} <= set(ONNX_DOMAINS)
            assert {n.op_type for n in nodes} <= EXPORTED_OPS, opset
            used |= {n.op_type for n in nodes}
            onnx_model_from_bytes(blob, f"opset {opset}")
    assert used == EXPORTED_OPS  # no operator listed that the exporter never writes
