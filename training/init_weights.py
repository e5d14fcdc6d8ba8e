"""Initial weights for fine-tuning: a DimeNet state dict and its spec from the bundled default
model, a RUN_DIR or an exported ``dimenet-model/1`` ONNX file.

From ONNX, the file is first loaded as the runtime loads it (``onnx_model_from_bytes``: at most
MAX_MODEL_BYTES, only the exporter's operators, every tensor float32 and in the file, as many
values as its shape), then the three weight matrices are read from the graph's initializers
with the ``onnx`` package (never pickle). The exporter (``export.onnx_export``) writes each
``nn.Linear`` as a ``MatMul`` by an (in, out) initializer, the transpose of torch's (out, in)
weight, and ends the graph with a ``Mul`` by the scalar constant OUTPUT_SCALE_PX; at opset >= 20
GELU is one ``Gelu`` node, below it is spelled out with Div/Erf/Add/Mul by scalar constants. A
scale folded into the last matrix is read too. The recovered weights are
then checked against the graph itself: torch on them must match ONNX Runtime on probe
features (as export's parity check), so a graph that is not this MLP is refused, never
silently misread.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import onnx
import torch
from onnx import helper, numpy_helper

from dimenet.runtime.errors import ModelError
from dimenet.runtime.rectify.model import OnnxModel, onnx_model_from_bytes, resolve_model
from dimenet.runtime.rectify.spec import ModelSpec

from .model import OUTPUT_SCALE_PX, DimeNet, dime_net
from .run_dir import load_run

LAYERS = ("fc1", "fc2", "fc3")
# Largest |Delta K| difference allowed between torch on the recovered weights and ONNX Runtime
# on the graph, on PROBE_FRAMES normal probe features: as export's parity check.
PARITY_TOLERANCE_PX = 1e-3
PARITY_RELATIVE = 1e-5
PROBE_FRAMES = 16


@dataclass(frozen=True)
class InitialWeights:
    """state_dict: name -> float32 torch.Tensor, the keys and (out, in) shapes of
    ``DimeNet.state_dict()`` (fc1.weight, fc2.weight, fc3.weight; the network's output is
    ``fc3(...) * OUTPUT_SCALE_PX`` px); spec: the model's spec; source: as passed to
    ``initial_weights``."""

    state_dict: dict
    spec: ModelSpec
    source: str


def _constants(graph: onnx.GraphProto) -> dict:
    """name -> numpy array of every initializer and every ``Constant`` node's output."""
    values = {init.name: numpy_helper.to_array(init) for init in graph.initializer}
    for node in graph.node:
        if node.op_type == "Constant" and len(node.attribute) == 1 and node.output:
            value = helper.get_attribute_value(node.attribute[0])
            if isinstance(value, onnx.TensorProto):
                values[node.output[0]] = numpy_helper.to_array(value)
            elif isinstance(value, (int, float, list)):
                values[node.output[0]] = np.asarray(value)
    return values


def _matrix(node: onnx.NodeProto, constants: dict, source: str) -> Optional[np.ndarray]:
    """The (out, in) float64 weight a MatMul node multiplies by, None for another node.
    ModelError for a weight that is no constant matrix."""
    if node.op_type != "MatMul":
        return None
    where = f"{source}: {node.op_type} node {node.name or node.output[0]!r}"
    if len(node.input) < 2 or node.input[1] not in constants:
        raise ModelError(f"{where} multiplies by no constant matrix: not a DIME-Net graph")
    weight = np.asarray(constants[node.input[1]], dtype=np.float64)
    if weight.ndim != 2:
        raise ModelError(f"{where} multiplies by a {weight.ndim}-D constant, expected a matrix")
    return weight.T


def _output_scale(nodes: list, constants: dict, source: str) -> float:
    """The product of the scalar factors the nodes after the last matrix apply (1 for none):
    each a Constant, or a Mul or Div by one scalar constant."""
    scale = 1.0
    for node in nodes:
        if node.op_type == "Constant":
            continue
        factors = [name for name in node.input if name in constants]
        if (
            node.op_type not in ("Mul", "Div")
            or len(factors) != 1
            or np.size(constants[factors[0]]) != 1
            or (node.op_type == "Div" and node.input[1] != factors[0])
        ):
            raise ModelError(
                f"{source}: after its last weight matrix the graph has the {node.op_type} node "
                f"{node.name or node.output[0]!r}, expected only the output scale (Mul by a scalar constant)"
            )
        factor = float(np.asarray(constants[factors[0]], dtype=np.float64).item())
        if not (np.isfinite(factor) and factor != 0.0):
            raise ModelError(f"{source}: the graph scales its output by {factor}, expected a finite non-zero factor")
        scale = scale * factor if node.op_type == "Mul" else scale / factor
    return scale


def _gated_state_dict(graph: onnx.GraphProto, constants: dict, spec: ModelSpec, source: str) -> dict:
    """The state dict of the gated step head's graph (``training.model``): its MatMuls are fc1, fc2,
    fc3 in graph order and the step pick (the one that reads the graph's input and gives 4 values);
    the gate is one Gemm (weight (4, h2) with transB = 1, bias (4,)); the output scale is the last
    node, a Mul by OUTPUT_SCALE_PX. Any other layout is a ModelError (and ``check_parity`` checks the rest)."""
    graph_input = graph.input[0].name
    matrices, pick = [], None
    for node in graph.node:
        weight = _matrix(node, constants, source)
        if weight is not None and node.input[0] == graph_input and weight.shape[0] == 4:
            pick = weight.T
        elif weight is not None:
            matrices.append(weight)
    gemms = [node for node in graph.node if node.op_type == "Gemm"]
    sizes = (spec.features.size, *spec.hidden, 4)
    expected = [(sizes[k + 1], sizes[k]) for k in range(3)]
    if pick is None or len(gemms) != 1 or [tuple(m.shape) for m in matrices] != expected:
        raise ModelError(
            f"{source}: its spec says head gated_step, but the graph does not hold three matrices of (out, in) "
            f"shapes {expected}, one step pick and one gate"
        )
    gate = gemms[0]
    trans_b = [helper.get_attribute_value(a) for a in gate.attribute if a.name == "transB"]
    weight, bias = (constants.get(name) for name in gate.input[1:3])
    if trans_b != [1] or weight is None or bias is None or np.shape(weight) != (4, sizes[2]) or np.shape(bias) != (4,):
        raise ModelError(f"{source}: its gate is not a Gemm of a (4, {sizes[2]}) weight (transB = 1) and a (4,) bias")
    last = graph.node[-1]
    if _output_scale([last], constants, source) != OUTPUT_SCALE_PX:
        raise ModelError(f"{source}: a gated step head's graph ends with a Mul by {OUTPUT_SCALE_PX:g}")
    tensors = {f"{name}.weight": m for name, m in zip(LAYERS, matrices)}
    tensors |= {"gate.weight": weight, "gate.bias": bias, "step_pick": pick}
    return {name: torch.from_numpy(np.array(v, dtype=np.float32)) for name, v in tensors.items()}


def onnx_state_dict(proto: onnx.ModelProto, spec: ModelSpec, source: str) -> dict:
    """The DimeNet state dict (float32 tensors, (out, in)) held by an exported graph: its three
    matrices in graph order, the output scale taken out of the last one (it stays OUTPUT_SCALE_PX
    in DimeNet.forward). ModelError naming ``source`` unless the graph holds exactly three
    bias-free matrices of the spec's sizes (features.size -> hidden -> 4)."""
    graph = proto.graph
    constants = _constants(graph)
    if spec.head == "gated_step":
        return _gated_state_dict(graph, constants, spec, source)
    matrices, last = [], -1
    for k, node in enumerate(graph.node):
        weight = _matrix(node, constants, source)
        if weight is not None:
            matrices.append(weight)
            last = k
        elif node.op_type != "Constant":
            big = [name for name in node.input if name in constants and np.size(constants[name]) != 1]
            if big:
                raise ModelError(
                    f"{source}: its {node.op_type} node {node.name or node.output[0]!r} reads the constant "
                    f"{big[0]!r} of shape {list(np.shape(constants[big[0]]))}: DIME-Net's graph reads "
                    f"non-scalar constants only as the weights of its three MatMuls (it has no biases)"
                )
    if len(spec.hidden) != 2:
        raise ModelError(f"{source}: its spec has {len(spec.hidden)} hidden layers {list(spec.hidden)}, DimeNet has 2")
    sizes = (spec.features.size, *spec.hidden, 4)
    expected = [(sizes[k + 1], sizes[k]) for k in range(3)]
    found = [tuple(m.shape) for m in matrices]
    if found != expected:
        raise ModelError(
            f"{source}: the graph multiplies by {len(matrices)} matrices of (out, in) shapes {found}, "
            f"its spec's MLP needs 3 of {expected} (features {sizes[0]}, hidden {list(spec.hidden)}, Delta K 4)"
        )
    if not all(np.all(np.isfinite(m)) for m in matrices):
        raise ModelError(f"{source}: a weight matrix holds non-finite values")
    matrices[-1] = matrices[-1] * (_output_scale(list(graph.node)[last + 1 :], constants, source) / OUTPUT_SCALE_PX)
    return {
        f"{name}.weight": torch.from_numpy(np.ascontiguousarray(m, np.float32)) for name, m in zip(LAYERS, matrices)
    }


def _model(state_dict: dict, spec: ModelSpec) -> DimeNet:
    model = dime_net(spec.features, spec.hidden, spec.head)
    model.load_state_dict(state_dict)
    return model.eval()


def check_parity(state_dict: dict, onnx_model: OnnxModel) -> None:
    """ModelError unless DimeNet with ``state_dict`` matches the ONNX graph on probe features
    (PARITY_TOLERANCE_PX + PARITY_RELATIVE x the largest |Delta K|) and on zero features exactly."""
    spec = onnx_model.spec
    probe = np.random.default_rng(0).normal(size=(PROBE_FRAMES, spec.features.size)).astype(np.float32)
    probe[0] = 0.0
    with torch.no_grad():
        expected = _model(state_dict, spec)(torch.from_numpy(probe)).numpy()
    got = onnx_model.delta_k(probe)
    worst = float(np.abs(got - expected).max())
    if not worst <= PARITY_TOLERANCE_PX + PARITY_RELATIVE * float(np.abs(got).max()) or np.any(got[0] != 0):
        raise ModelError(
            f"{onnx_model.source}: the weights read from the graph do not reproduce it (Delta K differs by up to "
            f"{worst:.2e} px): not a DIME-Net graph (three bias-free matrices with GELU between them)"
        )


def onnx_initial_weights(blob: bytes, source: str) -> tuple[dict, ModelSpec]:
    """The state dict and spec of a ``dimenet-model/1`` file's bytes: loaded and checked as the
    runtime loads it (``onnx_model_from_bytes``), its weights read and checked against it."""
    onnx_model = onnx_model_from_bytes(blob, source)
    try:
        proto = onnx.load_from_string(blob)
    except Exception as exc:  # protobuf's DecodeError and the onnx package's own errors
        raise ModelError(f"{source}: the onnx package cannot read it ({type(exc).__name__}: {exc})") from None
    state_dict = onnx_state_dict(proto, onnx_model.spec, source)
    check_parity(state_dict, onnx_model)
    return state_dict, onnx_model.spec


def initial_weights(source: str) -> InitialWeights:
    """Weights to start training from. ``source``: a bundled model's name (``resolve_model``; a folder of
    that name: "./default"), a RUN_DIR (weights.safetensors +
    spec.json) or a MODEL.onnx file from `dimenet export`. Raises ModelError naming the source."""
    ref = resolve_model(source)
    if ref.run_dir:
        model, spec = load_run(ref.path)
        state_dict = {k: v.detach().clone().to(torch.float32) for k, v in model.state_dict().items()}
        return InitialWeights(state_dict=state_dict, spec=spec, source=source)
    state_dict, spec = onnx_initial_weights(ref.model_bytes(), ref.source)
    return InitialWeights(state_dict=state_dict, spec=spec, source=source)
