"""Freeze a trained DIME-Net into a ``dimenet-model/1`` ONNX file (needs the ``export`` extra: onnx).

The graph maps ``features`` float32 [batch, D] (dynamic batch) to ``delta_k`` float32
[batch, 4] px; the model spec JSON rides in ``metadata_props`` under ``METADATA_KEY``.
The exported bytes are checked (onnx.checker, then ONNX Runtime against torch on probe
features, and zero features -> exactly zero Delta K) before anything is written, and the
file is written atomically: a failed export leaves any previous file intact. The spec carries
``weights_sha256`` (spec >= 1.4), the sha256 of the file's bytes with that value set to 64
zeros (``stamp_weights_sha256``), which the runtime checks without the onnx package.
"""

from __future__ import annotations

import hashlib
import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch

from dimenet.runtime.errors import ModelError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.rectify.integrity import content_sha256
from dimenet.runtime.rectify.model import (
    INPUT_NAME,
    OUTPUT_NAME,
    onnx_model_from_bytes,
    stamped_digests,
    weights_sha256_span,
)
from dimenet.runtime.rectify.onnx_graph import check_model_bytes
from dimenet.runtime.rectify.ort_format import ORT_SHA256_KEY, ort_sha256_span
from dimenet.runtime.rectify.spec import (
    CONTENT_SHA256_KEY,
    METADATA_KEY,
    WEIGHTS_SHA256_KEY,
    WEIGHTS_SHA256_PLACEHOLDER,
    ModelSpec,
)
from dimenet.training.model import DimeNet
from dimenet.training.run_dir import load_run

from .opset import DEFAULT_OPSET, MAX_OPSET, MIN_OPSET

# Largest |Delta K| difference allowed between ONNX Runtime and torch on the probe features:
# PARITY_TOLERANCE_PX plus float32 rounding, PARITY_RELATIVE times the largest |Delta K|.
PARITY_TOLERANCE_PX = 1e-3
PARITY_RELATIVE = 1e-5
PROBE_FRAMES = 16


def _trace(model: DimeNet, size: int, opset: int) -> bytes:
    """The MLP as ONNX bytes from the TorchScript exporter (a small, plain MatMul/Erf graph)."""
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter announces its deprecation
        torch.onnx.export(
            model.eval(),
            (torch.zeros(1, size),),
            buf,
            dynamo=False,
            opset_version=opset,
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME],
            do_constant_folding=True,
            dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
        )
    return buf.getvalue()


def _stamped(blob: bytes, span_of, key: str) -> bytes:
    """Model bytes holding the placeholder of the stamp ``key`` (64 zeros, found by ``span_of(blob,
    digits)``) -> the same bytes with those zeros replaced by the sha256 of ``blob`` (same length: the
    protobuf or flatbuffer lengths stay valid). The runtime undoes the replacement and compares
    (``rectify.model.stamped_digests``)."""
    span = span_of(blob, WEIGHTS_SHA256_PLACEHOLDER)
    if span is None:
        raise ModelError(f"export: the placeholder {key} does not occur exactly once in the model's bytes")
    digest = hashlib.sha256(blob).hexdigest()
    stamped = blob[: span[0]] + digest.encode("ascii") + blob[span[1] :]
    if stamped_digests(stamped, span_of(stamped, digest)) != (digest, hashlib.sha256(stamped).hexdigest()):
        raise ModelError(f"export: the stamped {key} does not verify")
    return stamped


def stamp_weights_sha256(blob: bytes) -> bytes:
    """ONNX bytes whose spec holds ``weights_sha256`` = 64 zeros -> the same bytes stamped (``_stamped``)."""
    return _stamped(blob, weights_sha256_span, WEIGHTS_SHA256_KEY)


def stamp_ort_sha256(blob: bytes) -> bytes:
    """ORT-format bytes whose metadata holds ``ORT_SHA256_KEY`` = 64 zeros -> the same bytes stamped
    (``_stamped``): the hash that covers the graph, which content_sha256 leaves out."""
    return _stamped(blob, ort_sha256_span, ORT_SHA256_KEY)


def stamp_content_sha256(blob: bytes) -> bytes:
    """Model bytes whose spec holds ``content_sha256`` = 64 zeros -> the same bytes with those zeros
    replaced by the content digest of the spec and the graph's tensors (``rectify.integrity``)."""
    proto = onnx.load_from_string(blob)
    text = next(p.value for p in proto.metadata_props if p.key == METADATA_KEY)
    digest = content_sha256(text, check_model_bytes(blob, "exported model"))
    entry = f'"{CONTENT_SHA256_KEY}": "{WEIGHTS_SHA256_PLACEHOLDER}"'.encode("ascii")
    if blob.count(entry) != 1:
        raise ModelError("export: the placeholder content_sha256 does not occur exactly once in the model's bytes")
    return blob.replace(entry, f'"{CONTENT_SHA256_KEY}": "{digest}"'.encode("ascii"))


def _with_spec(blob: bytes, spec: ModelSpec) -> bytes:
    """The model bytes with the spec JSON in metadata_props, after onnx.checker (full check),
    stamped with its content_sha256, then its weights_sha256 (``stamp_content_sha256``,
    ``stamp_weights_sha256``)."""
    proto = onnx.load_from_string(blob)
    del proto.metadata_props[:]
    entry = proto.metadata_props.add()
    placeholder = WEIGHTS_SHA256_PLACEHOLDER
    entry.key, entry.value = METADATA_KEY, spec.to_json(weights_sha256=placeholder, content_sha256=placeholder)
    proto.doc_string = f"DIME-Net: grid feature -> Delta K (px); model spec in metadata_props[{METADATA_KEY!r}]"
    try:
        onnx.checker.check_model(proto, full_check=True)
    except onnx.checker.ValidationError as exc:
        raise ModelError(f"export: the exported graph fails onnx.checker ({str(exc).splitlines()[0]})") from None
    return stamp_weights_sha256(stamp_content_sha256(proto.SerializeToString()))


def _check_parity(model: DimeNet, blob: bytes, size: int) -> None:
    """ModelError unless ONNX Runtime matches torch (see PARITY_TOLERANCE_PX) and f(0) = 0 exactly."""
    probe = np.random.default_rng(0).normal(size=(PROBE_FRAMES, size)).astype(np.float32)
    probe[0] = 0.0
    with torch.no_grad():
        expected = model(torch.from_numpy(probe)).numpy()
    got = onnx_model_from_bytes(blob, "exported model").delta_k(probe)
    worst = float(np.abs(got - expected).max())
    if not worst <= PARITY_TOLERANCE_PX + PARITY_RELATIVE * float(np.abs(expected).max()):
        raise ModelError(
            f"export: ONNX Runtime and torch differ by up to {worst:.2e} px "
            f"(allowed {PARITY_TOLERANCE_PX} px + {PARITY_RELATIVE:g} x the largest |Delta K|)"
        )
    if np.any(got[0] != 0.0):
        raise ModelError(f"export: zero features give Delta K {got[0].tolist()} px in ONNX, expected exactly 0")


def export_model(model: DimeNet, spec: ModelSpec, *, opset: int = DEFAULT_OPSET) -> bytes:
    """The checked ``dimenet-model/1`` ONNX bytes of a DimeNet and its spec."""
    if not MIN_OPSET <= opset <= MAX_OPSET:
        raise ModelError(f"export: opset must be {MIN_OPSET} to {MAX_OPSET}, got {opset}")
    size = spec.features.size
    if model.fc1.in_features != size:
        raise ModelError(f"export: the model reads {model.fc1.in_features} features, its spec's feature has {size}")
    try:
        traced = _trace(model, size, opset)
    except Exception as exc:  # the exporter raises assorted types, e.g. for an unsupported opset
        raise ModelError(f"export: torch.onnx.export failed at opset {opset} ({type(exc).__name__}: {exc})") from None
    blob = _with_spec(traced, spec)
    _check_parity(model, blob, size)
    return blob


def restamp_model(blob: bytes, source: str = "model") -> bytes:
    """A ``dimenet-model/1`` file's bytes with its spec re-embedded at this release's spec
    version and stamped with its weights_sha256; graph, weights and spec content untouched.
    The input must load (``onnx_model_from_bytes``), and so must the result."""
    spec = onnx_model_from_bytes(blob, source).spec
    stamped = _with_spec(blob, spec)
    onnx_model_from_bytes(stamped, f"{source} (re-stamped)")
    return stamped


def ort_format_bytes(blob: bytes, source: str = "model") -> bytes:
    """An ORT-format (ORT Mobile) conversion of ``dimenet-model/1`` ONNX bytes of spec >= 1.9, by ONNX
    Runtime itself with its graph optimizations off, so the converted file keeps the graph's nodes
    and tensors (its Constant nodes become initializers of the same name and values) and its spec,
    and is stamped with its own ORT_SHA256_KEY beside the spec (``stamp_ort_sha256``): it loads with
    both hashes checked (``rectify.model``) and gives the same Delta K."""
    import tempfile

    import onnxruntime as ort

    model = onnx_model_from_bytes(blob, source)
    if model.spec.content_sha256 is None:
        raise ModelError(f"{source}: its spec (before 1.9) has no content_sha256: re-stamp or re-export it first")
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    options.add_session_config_entry("session.save_model_format", "ORT")
    proto = onnx.load_from_string(blob)
    entry = proto.metadata_props.add()
    entry.key, entry.value = ORT_SHA256_KEY, WEIGHTS_SHA256_PLACEHOLDER
    with tempfile.TemporaryDirectory() as folder:
        options.optimized_model_filepath = str(Path(folder) / "model.ort")
        ort.InferenceSession(proto.SerializeToString(), options, providers=["CPUExecutionProvider"])
        converted = stamp_ort_sha256((Path(folder) / "model.ort").read_bytes())
    loaded = onnx_model_from_bytes(converted, f"{source} (ORT format)")
    probe = np.random.default_rng(0).normal(size=(PROBE_FRAMES, model.spec.features.size)).astype(np.float32)
    worst = float(np.abs(loaded.delta_k(probe) - model.delta_k(probe)).max())
    if not worst <= PARITY_TOLERANCE_PX:
        raise ModelError(
            f"export: the ORT-format conversion of {source} gives a Delta K up to {worst:.2e} px off the ONNX file's"
        )
    return converted


def run_model_bytes(run_dir: str | Path, *, opset: int = DEFAULT_OPSET) -> bytes:
    """The checked ``dimenet-model/1`` ONNX bytes of a RUN_DIR from `dimenet train`."""
    model, spec = load_run(run_dir)
    return export_model(model, spec, opset=opset)


def export_run(run_dir: str | Path, out: str | Path, *, opset: int = DEFAULT_OPSET) -> Path:
    """Export a RUN_DIR from `dimenet train` to ``out`` (.onnx), atomically. Returns ``out``."""
    blob = run_model_bytes(run_dir, opset=opset)
    return atomic_write(out, lambda f: f.write(blob))
