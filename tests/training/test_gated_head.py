"""The gated step head (ModelSpec.head "gated_step", training.model): Delta K = the MLP's + a learned
share of the frame's own data step, exactly 0 for a zero feature, exported with parity, read back
for fine-tuning, and refused without the data step it gates."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from dimenet.export.onnx_export import export_model
from dimenet.runtime.errors import ModelError
from dimenet.runtime.geometry import k_matrix
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import onnx_model_from_bytes
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.training.init_weights import onnx_initial_weights
from dimenet.training.model import GATE_START, dime_net


@pytest.fixture(scope="module")
def spec() -> ModelSpec:
    return ModelSpec(
        features=FeatureSpec(grid=Grid(2, 2), data_step=True),
        K_c=k_matrix([3000.0, 3000.0, 2016.0, 1512.0]),
        image_size=(4032, 3024),
        K_bounds=np.array([[2900.0, 3100.0], [2900.0, 3100.0], [1900.0, 2100.0], [1400.0, 1600.0]]),
        hidden=(8, 8),
        head="gated_step",
    )


def test_the_head_adds_the_gated_step_in_px_and_zero_stays_zero(spec):
    torch.manual_seed(0)
    net = dime_net(spec.features, spec.hidden, spec.head).eval()
    with torch.no_grad():
        net.fc3.weight.zero_()  # the MLP's own term off: only the gated step remains
        features = torch.zeros(2, spec.features.size)
        step_px = torch.tensor([1.5, -2.0, 3.0, 0.25])
        features[1, spec.features.grid_size : spec.features.grid_size + 4] = step_px * spec.features.scale["dx"]
        features[1, :4] = 0.3  # the grid moves the gate's hidden input, not the step
        out = net(features)
        gate = torch.sigmoid(net.gate(net.act(net.fc2(net.act(net.fc1(features[1:]))))))[0]
    assert torch.all(out[0] == 0)
    torch.testing.assert_close(out[1], gate * step_px, rtol=1e-5, atol=1e-6)
    fresh = dime_net(spec.features, spec.hidden, spec.head)
    assert torch.all(fresh.gate.bias == GATE_START) and not fresh.step_pick.requires_grad


def test_export_keeps_parity_and_fine_tuning_reads_the_same_weights(spec):
    torch.manual_seed(1)
    net = dime_net(spec.features, spec.hidden, spec.head).eval()
    blob = export_model(net, spec)
    loaded = onnx_model_from_bytes(blob, "gated")
    assert loaded.spec.head == "gated_step"
    probe = np.random.default_rng(3).normal(size=(5, spec.features.size)).astype(np.float32)
    with torch.no_grad():
        expected = net(torch.from_numpy(probe)).numpy()
    np.testing.assert_allclose(loaded.delta_k(probe), expected, atol=1e-4)
    state, read_spec = onnx_initial_weights(blob, "gated")
    assert read_spec.head == "gated_step"
    for name, value in net.state_dict().items():
        torch.testing.assert_close(state[name], value, rtol=0, atol=0)


def test_a_gated_head_needs_the_data_step():
    spec_dict = {
        "format": "dimenet-model/1",
        "version": "1.8.0",
        "features": {"grid": "2x2", "variant": "A", "scale": FeatureSpec().scale},
        "K_c": [3000.0, 3000.0, 2016.0, 1512.0],
        "image_size": [4032, 3024],
        "K_bounds": [[2900.0, 3100.0], [2900.0, 3100.0], [1900.0, 2100.0], [1400.0, 1600.0]],
        "hidden": [8, 8],
        "head": "gated_step",
    }
    with pytest.raises(ModelError, match="head gated_step needs features.data_step"):
        ModelSpec.from_dict(spec_dict)
    with pytest.raises(ModelError, match="head must be one of mlp, gated_step, got 'wide'"):
        ModelSpec.from_dict({**spec_dict, "head": "wide"})
    stepped = ModelSpec.from_dict({**spec_dict, "features": {**spec_dict["features"], "data_step": True}})
    assert stepped.head == "gated_step" and ModelSpec.from_dict(stepped.to_dict()).head == "gated_step"
    assert "head" not in replace(stepped, head="mlp").to_dict()


def test_a_training_config_states_the_head_rule_in_the_command_s_words():
    from dimenet.runtime.errors import InputError
    from dimenet.training.config import TrainConfig

    with pytest.raises(InputError, match=r"head gated_step needs --data-step \(data_step in a fleet manifest\)"):
        TrainConfig(head="gated_step")
    with pytest.raises(InputError, match="head must be one of mlp, gated_step, got 'wide'"):
        TrainConfig(head="wide", features=FeatureSpec(data_step=True))
    assert TrainConfig(head="gated_step", features=FeatureSpec(data_step=True)).head == "gated_step"
