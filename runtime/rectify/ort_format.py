"""What an ORT-format model file (``.ort``, ORT Mobile's; `dimenet export --format ort`) may hold,
checked on its bytes before ONNX Runtime sees them, as ``rectify.onnx_graph`` checks an ONNX file:
every node one of ``EXPORTED_OPS`` in the default ONNX domain (``onnx_graph.check_operator``), no
subgraph, every initializer float32 with its values in the file, as many as its dims say, no sparse
initializer. The flatbuffer is read with the classes onnxruntime ships
(``onnxruntime.tools.ort_format_model``; flatbuffers is one of onnxruntime's own requirements).
Returns the constant tensors, which the content hash covers (``rectify.integrity``): the conversion
turns the ONNX file's Constant nodes into initializers of their output's name, so the two files hold
the same tensors.

The content hash leaves out the graph (its operators, wiring and attributes), so an ORT-format file
also carries ``ORT_SHA256_KEY`` in its metadata: the sha256 of the file's bytes with that value set
to 64 zeros, as ``weights_sha256`` is an ONNX file's (``rectify.model.stamped_digests``). It sits
beside the spec, not in it, so the spec text and its ``content_sha256`` stay the ONNX file's.
"""

from __future__ import annotations

import struct
from typing import Optional

from dimenet.runtime.errors import ModelError
from dimenet.runtime.json_text import shown
from dimenet.runtime.rectify.onnx_graph import Tensor, check_operator, check_size, float_tensor

ORT_IDENTIFIER = b"ORTM"  # bytes 4-8 of every ORT-format file (its flatbuffer file identifier)
FLOAT = 1  # fbs TensorDataType.FLOAT
# The metadata entry holding the ORT-format file's own hash: 64 lowercase hex digits (module doc).
ORT_SHA256_KEY = "dimenet_ort_sha256"


def is_ort_format(blob: bytes) -> bool:
    """Whether the bytes are an ORT-format model (by the flatbuffer's file identifier)."""
    return blob[4:8] == ORT_IDENTIFIER


def ort_sha256_span(blob: bytes, digest: str) -> Optional[tuple]:
    """(start, end) of the 64 hex digits ``digest`` as a flatbuffer string in the bytes (its length 64
    as uint32 little-endian, the digits, a NUL: how the file holds ``ORT_SHA256_KEY``'s value), or
    None unless that string occurs exactly once."""
    value = digest.encode("utf-8")
    entry = struct.pack("<I", len(value)) + value + b"\0"
    if blob.count(entry) != 1:
        return None
    start = blob.find(entry) + 4
    return start, start + len(value)


def _tensor(t, what: str) -> Tensor:
    name = (t.Name() or b"").decode("utf-8", "replace")
    label = f"{what} {shown(name)}"
    if t.DataType() != FLOAT:
        raise ModelError(f"{label} has ORT data type {t.DataType()}: the exporter writes float32 (1) tensors only")
    if getattr(t, "ExternalDataOffset", lambda: -1)() >= 0:  # the field is newer than onnxruntime 1.19
        raise ModelError(f"{label} keeps its values outside the file's tensor: a model file holds its weights inline")
    dims = t.DimsAsNumpy().tolist() if t.DimsLength() else []
    return float_tensor(label, name, dims, t.RawDataAsNumpy().tobytes() if t.RawDataLength() else b"")


def check_ort_bytes(blob: bytes, source: str) -> list:
    """ModelError naming ``source`` unless the ORT-format bytes hold only what the exporter writes;
    returns the graph's initializers (``Tensor``)."""
    check_size(blob, source)
    from onnxruntime.tools.ort_format_model.ort_flatbuffers_py import fbs

    try:
        graph = fbs.InferenceSession.InferenceSession.GetRootAs(blob, 0).Model().Graph()
        if graph.SparseInitializersLength():
            raise ModelError("the graph has a sparse initializer: the exporter writes none")
        for k in range(graph.NodesLength()):
            node = graph.Nodes(k)
            name = (node.Name() or b"").decode("utf-8", "replace")
            op_type = (node.OpType() or b"").decode("utf-8", "replace")
            domain = (node.Domain() or b"").decode("utf-8", "replace")
            where = f"node {k} ({shown(name)})"
            check_operator(where, op_type, domain)
            for j in range(node.AttributesLength()):
                attribute = node.Attributes(j)
                if attribute.G() is not None or attribute.GraphsLength():
                    raise ModelError(f"{where} holds a subgraph: a DIME-Net graph has no control flow")
        return [_tensor(graph.Initializers(k), "initializer") for k in range(graph.InitializersLength())]
    except ModelError as exc:
        raise ModelError(f"{source}: {exc}") from None
    except Exception as exc:  # a truncated or crafted flatbuffer: struct.error, IndexError, UnicodeError, ...
        raise ModelError(f"{source}: not a loadable ORT-format model ({type(exc).__name__}: {exc})") from None
