"""What a ``dimenet-model/1`` ONNX file may hold, checked on its bytes before ONNX Runtime sees
them (a protobuf walk of the few ONNX messages involved: no onnx package, no protobuf classes).

A model file holds its own weights and the graph the exporter writes, nothing more:
- at most MAX_MODEL_BYTES, and at most MAX_FIELDS protobuf fields and packed values (the
  bundled model has about 250; the bound keeps the walk of a hostile file under 0.1 s);
- every node one of EXPORTED_OPS in the default ONNX domain: no control flow, no subgraph
  (an ``If`` or a ``Loop`` of 2**60 iterations would make the load-time probe run for ever),
  no model-local function, no training information;
- every tensor (initializers and ``Constant`` values) float32, its values in the file itself
  (never ``data_location`` EXTERNAL or ``external_data``, which ONNX Runtime would resolve
  against the process's current folder, outside ``weights_sha256``; never a ``segment``), and
  exactly as many values as its dims declare; no sparse tensor.
Anything else is a ModelError naming the file. See models_spec/model-v1.md, "Versioning".
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

from dimenet.runtime.errors import ModelError
from dimenet.runtime.json_text import shown

MAX_MODEL_BYTES = 64 << 20  # 3x the largest model `dimenet train` makes (64x64 grid, variant A: 21 MB)
MAX_FIELDS = 100_000
# The operators `dimenet export` writes (export.onnx_export, every opset it offers): three MatMuls,
# exact GELU (one Gelu node at opset >= 20, else Div/Erf/Add/Mul by scalar Constants) and the
# output scale (Mul); the gated step head (spec >= 1.8) adds a MatMul picking the step, the gate's
# Gemm or MatMul/Add, and its Sigmoid.
EXPORTED_OPS = frozenset({"Add", "Constant", "Div", "Erf", "Gelu", "Gemm", "MatMul", "Mul", "Sigmoid"})
ONNX_DOMAINS = ("", "ai.onnx")
FLOAT = 1  # TensorProto.FLOAT
EXTERNAL = 1  # TensorProto.EXTERNAL

# Field numbers of onnx.proto (stable across IR versions).
_MODEL_GRAPH, _MODEL_TRAINING_INFO, _MODEL_FUNCTIONS = 7, 20, 25
_GRAPH_NODE, _GRAPH_INITIALIZER, _GRAPH_SPARSE_INITIALIZER = 1, 5, 15
_NODE_OUTPUT, _NODE_NAME, _NODE_OP_TYPE, _NODE_ATTRIBUTE, _NODE_DOMAIN = 2, 3, 4, 5, 7
_ATTRIBUTE_TENSORS = (5, 10)  # t, tensors
_ATTRIBUTE_GRAPHS = (6, 11)  # g, graphs
_ATTRIBUTE_SPARSE = (22, 23)  # sparse_tensor, sparse_tensors
_TENSOR_DIMS, _TENSOR_DATA_TYPE, _TENSOR_SEGMENT, _TENSOR_FLOAT_DATA, _TENSOR_NAME, _TENSOR_RAW_DATA = 1, 2, 3, 4, 8, 9
_TENSOR_OTHER_DATA = (5, 6, 7, 10, 11)  # int32, string, int64, double, uint64 values
_TENSOR_EXTERNAL_DATA, _TENSOR_DATA_LOCATION = 13, 14


@dataclass(frozen=True)
class Tensor:
    """A constant tensor of a model file: its name (a Constant's: its output's), dims and float32
    values as little-endian bytes; what the content hash covers (``rectify.integrity``)."""

    name: str
    dims: tuple
    data: bytes


class _Malformed(ValueError):
    """The bytes are not a protobuf message."""


class _Budget:
    """The fields and packed values a walk may still read (MAX_FIELDS in all)."""

    def __init__(self) -> None:
        self.left = MAX_FIELDS

    def spend(self, n: int = 1) -> None:
        self.left -= n
        if self.left < 0:
            raise ModelError(f"more than {MAX_FIELDS} protobuf fields: a DIME-Net model has a few hundred")


def _varint(buf: memoryview, i: int) -> tuple[int, int]:
    if i < len(buf) and buf[i] < 0x80:  # one byte: most keys and lengths
        return buf[i], i + 1
    value = shift = 0
    for k in range(10):
        if i + k >= len(buf):
            raise _Malformed("truncated varint")
        byte = buf[i + k]
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, i + k + 1
        shift += 7
    raise _Malformed("varint longer than 10 bytes")


def _fields(buf: memoryview, budget: _Budget) -> Iterator[tuple[int, int, object]]:
    """(field number, wire type, value) of each field of one message: an int for a varint, a
    memoryview for a length-delimited or a fixed 32/64-bit field (its bytes)."""
    i, n = 0, len(buf)
    while i < n:
        budget.spend()
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise _Malformed("field number 0")
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire in (1, 5):
            value, i = buf[i : i + (8 if wire == 1 else 4)], i + (8 if wire == 1 else 4)
        elif wire == 2:
            length, i = _varint(buf, i)
            value, i = buf[i : i + length], i + length
        else:
            raise _Malformed(f"wire type {wire} (groups are not ONNX)")
        if i > n:
            raise _Malformed("a field runs past the end of its message")
        yield number, wire, value


def _text(value: memoryview) -> str:
    return bytes(value).decode("utf-8", "replace")


def _check_tensor(buf: memoryview, what: str, budget: _Budget, name: str = "") -> Tensor:
    """A float32 tensor whose values are all in its raw_data or float_data, as many as its dims say.
    ``name``: the tensor's name when its own is empty (a Constant's output)."""
    dims, data_type, location, raw, float_parts, other = [], 0, 0, None, [], set()
    for number, wire, value in _fields(buf, budget):
        if number == _TENSOR_NAME and wire == 2 and _text(value):
            name = _text(value)
        elif number == _TENSOR_DIMS and wire == 0:
            dims.append(value)
        elif number == _TENSOR_DIMS and wire == 2:
            dims += _packed_varints(value, budget)
        elif number == _TENSOR_DATA_TYPE and wire == 0:
            data_type = value
        elif number == _TENSOR_DATA_LOCATION and wire == 0:
            location = value
        elif number == _TENSOR_RAW_DATA and wire == 2:
            raw = value
        elif number == _TENSOR_FLOAT_DATA and wire in (2, 5):
            float_parts.append(value)  # little-endian float32 bytes (packed or one fixed32)
        elif number in (_TENSOR_EXTERNAL_DATA, _TENSOR_SEGMENT, *_TENSOR_OTHER_DATA):
            other.add(number)
    label = f"{what} {shown(name)}"
    if location == EXTERNAL or _TENSOR_EXTERNAL_DATA in other:
        raise ModelError(f"{label} keeps its values in an external file: a model file must hold its weights")
    if _TENSOR_SEGMENT in other:
        raise ModelError(f"{label} is a segment of a tensor: a model file holds whole tensors")
    if other:
        raise ModelError(f"{label} holds values in a field of another type than float32: the exporter writes none")
    if data_type != FLOAT:
        raise ModelError(f"{label} has ONNX data type {data_type}: the exporter writes float32 (1) tensors only")
    if raw is not None and float_parts:
        raise ModelError(f"{label} holds its values twice (raw_data and float_data)")
    data = bytes(raw) if raw is not None else b"".join(bytes(part) for part in float_parts)
    return float_tensor(label, name, dims, data)


def float_tensor(label: str, name: str, dims, data: bytes) -> Tensor:
    """The Tensor of a float32 tensor's dims and value bytes (little-endian), checked: no negative
    dimension (an ONNX file's unsigned varint at or above 2^63 is one) and as many values as the
    dims say; ModelError naming ``label`` (the rule of an ONNX file's tensors here, and of an
    ORT-format file's in ``rectify.ort_format``)."""
    dims = tuple(int(d) for d in dims)
    if any(d < 0 or d >= 1 << 63 for d in dims):
        raise ModelError(f"{label} declares a negative dimension")
    count = math.prod(dims)
    if len(data) != 4 * count:
        raise ModelError(f"{label} declares shape {list(dims)} ({count} float32 values) but holds {len(data)} bytes")
    return Tensor(name, dims, data)


def check_size(blob: bytes, source: str) -> None:
    """ModelError naming ``source`` when the bytes are more than MAX_MODEL_BYTES (any model file format)."""
    if len(blob) > MAX_MODEL_BYTES:
        raise ModelError(f"{source}: larger than {MAX_MODEL_BYTES} bytes, too large for a DIME-Net model")


def check_operator(node: str, op_type: str, domain: str) -> None:
    """ModelError naming ``node`` unless it is one of EXPORTED_OPS in the default ONNX domain (the
    rule of an ONNX file's nodes here, and of an ORT-format file's in ``rectify.ort_format``)."""
    if domain not in ONNX_DOMAINS or op_type not in EXPORTED_OPS:
        op = op_type if domain in ONNX_DOMAINS else f"{domain}:{op_type}"
        raise ModelError(
            f"{node} is the operator {shown(op)}, which `dimenet export` never writes "
            f"(a DIME-Net graph holds only {', '.join(sorted(EXPORTED_OPS))})"
        )


def _packed_varints(buf: memoryview, budget: _Budget) -> list:
    out, i = [], 0
    while i < len(buf):
        budget.spend()
        value, i = _varint(buf, i)
        out.append(value)
    return out


def _check_node(buf: memoryview, index: int, budget: _Budget) -> list:
    """The node's checks; the tensors its attributes hold, named after its first output."""
    name, op_type, domain, attributes, outputs = "", "", "", [], []
    for number, wire, value in _fields(buf, budget):
        if wire != 2:
            continue
        if number == _NODE_OUTPUT:
            outputs.append(_text(value))
        elif number == _NODE_NAME:
            name = _text(value)
        elif number == _NODE_OP_TYPE:
            op_type = _text(value)
        elif number == _NODE_DOMAIN:
            domain = _text(value)
        elif number == _NODE_ATTRIBUTE:
            attributes += _fields(value, budget)
    node = f"node {index} ({shown(name)})"
    numbers = {number for number, _, _ in attributes}
    if numbers & set(_ATTRIBUTE_GRAPHS):
        raise ModelError(f"{node} holds a subgraph: a DIME-Net graph has no control flow")
    if numbers & set(_ATTRIBUTE_SPARSE):
        raise ModelError(f"{node} holds a sparse tensor: the exporter writes none")
    check_operator(node, op_type, domain)
    output = outputs[0] if outputs else ""
    return [
        _check_tensor(value, f"the value of {node}", budget, output)
        for number, wire, value in attributes
        if number in _ATTRIBUTE_TENSORS and wire == 2
    ]


def _check_graph(buf: memoryview, nodes: int, budget: _Budget, tensors: list) -> int:
    """Checks one occurrence of the model's graph field, adding its tensors to ``tensors``;
    returns the count of nodes seen so far."""
    for number, wire, value in _fields(buf, budget):
        if wire != 2:
            continue
        if number == _GRAPH_NODE:
            tensors += _check_node(value, nodes, budget)
            nodes += 1
        elif number == _GRAPH_INITIALIZER:
            tensors.append(_check_tensor(value, "initializer", budget))
        elif number == _GRAPH_SPARSE_INITIALIZER:
            raise ModelError("the graph has a sparse initializer: the exporter writes none")
    return nodes


def check_model_bytes(blob: bytes, source: str) -> list:
    """ModelError naming ``source`` unless the ONNX bytes hold only what the exporter writes
    (see the module doc); bytes that are no protobuf message are "not a loadable ONNX model".
    Returns the graph's constant tensors (initializers and Constant values, ``Tensor``)."""
    check_size(blob, source)
    tensors: list = []
    try:
        nodes, budget = 0, _Budget()
        for number, wire, value in _fields(memoryview(blob), budget):
            if number == _MODEL_GRAPH and wire == 2:
                nodes = _check_graph(value, nodes, budget, tensors)
            elif number == _MODEL_FUNCTIONS:
                raise ModelError("the model defines functions: the exporter writes none")
            elif number == _MODEL_TRAINING_INFO:
                raise ModelError("the model holds training information: the exporter writes none")
    except _Malformed as exc:
        raise ModelError(f"{source}: not a loadable ONNX model (malformed protobuf: {exc})") from None
    except ModelError as exc:
        raise ModelError(f"{source}: {exc}") from None
    return tensors
