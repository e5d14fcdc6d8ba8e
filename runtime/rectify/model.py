"""An exported DIME-Net (``dimenet-model/1`` ONNX file) run by ONNX Runtime: features -> Delta K.

The file holds the frozen MLP (input ``features`` float32 [batch, D], output ``delta_k``
float32 [batch, 4] px as (dfx, dfy, dcx, dcy)) and its model spec as JSON in the ONNX
``metadata_props`` under ``METADATA_KEY``. Loading refuses, with a ModelError naming the file:
an unreadable or corrupt file, one past ``MAX_MODEL_BYTES``, a graph holding more than the
exporter writes (other operators, subgraphs, external data: ``rectify.onnx_graph``, checked on
the bytes before ONNX Runtime sees them), a foreign model without the spec, a spec of another major
version or malformed, a graph whose input or output does not match the spec (declared, or
as a probe call on zero features really gives), and bytes that differ from the spec's
``weights_sha256`` (spec >= 1.4); an ORT-format file also needs its spec's ``content_sha256`` and its
own ``ORT_SHA256_KEY`` (``rectify.ort_format``), both checked. Needs onnxruntime only (never onnx,
never torch). See models_spec/model-v1.md.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import numbers
import os
import re
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Protocol, runtime_checkable

import numpy as np
import onnxruntime as ort

from dimenet.runtime.assets import asset
from dimenet.runtime.errors import InputError, ModelError
from dimenet.runtime.rectify.integrity import content_sha256
from dimenet.runtime.rectify.onnx_graph import MAX_MODEL_BYTES, check_model_bytes
from dimenet.runtime.rectify.ort_format import ORT_SHA256_KEY, check_ort_bytes, is_ort_format, ort_sha256_span
from dimenet.runtime.rectify.spec import (
    CONTENT_SHA256_KEY,
    METADATA_KEY,
    WEIGHTS_SHA256_KEY,
    WEIGHTS_SHA256_PLACEHOLDER,
    ModelSpec,
)

# The bundled models (files in dimenet.runtime.assets) by the name that stands for a model path wherever
# one is taken ("./default": a file of that name): "default" (also named "any-scene"), the scene-robust
# encoder (the frame's own step and moments, the gated head) that holds on rigs, distances and scenes
# other than the paper's; "paper-rig", the paper's grid model, for its rig at its framing and for
# `dimenet reproduce` (training/METHOD.md, "The two bundled models"; 0.7.0 made any-scene the default).
BUNDLED_MODELS = {
    "default": "any_scene_model.onnx",
    "any-scene": "any_scene_model.onnx",
    "paper-rig": "paper_rig_model.onnx",
}
DEFAULT_NAME = "default"
# One name per bundled file, for whatever is done once per model (golden sets, fuzz, reports).
MODEL_NAMES = ("default", "paper-rig")
# How the commands' help names the bundled models.
BUNDLED_HELP = "default (the any-scene encoder, also named any-scene) or paper-rig (the paper's grid model)"
DEFAULT_MODEL = BUNDLED_MODELS[DEFAULT_NAME]
# Most ONNX Runtime intra-op threads a session may ask for: more only contend for the cores (the CLI's
# --threads and --workers take the same cap); 10**6 threads crash the process, 10**5 spin for minutes.
MAX_THREADS = 4 * (os.cpu_count() or 1)

INPUT_NAME = "features"
OUTPUT_NAME = "delta_k"
DEFAULT_PROVIDERS = ("CPUExecutionProvider",)
PROBE_FRAMES = 2  # the batch of zero features the load-time probe call runs


@runtime_checkable
class DeltaKModel(Protocol):
    """Features -> Delta K, what a model is to the rectifier and the evaluation (``OnnxModel``, the evaluation's
    ``Predictor``): its spec, how errors name it, a batch (B, D) float32 -> (B, 4) px and one frame's (1, D) ->
    (4,) float64 px."""

    spec: ModelSpec
    source: str

    def delta_k(self, features: np.ndarray) -> np.ndarray: ...

    def frame_delta_k(self, features: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class OnnxModel:
    """A loaded model: its ORT session, spec, where it came from and the sha256 of its bytes."""

    session: ort.InferenceSession
    spec: ModelSpec
    source: str
    sha256: str
    _frame_io: threading.local = field(default_factory=threading.local, init=False, repr=False, compare=False)

    def delta_k(self, features: np.ndarray) -> np.ndarray:
        """features (B, D) float32 -> Delta K (B, 4) float32 px, one ORT call."""
        return self.session.run((OUTPUT_NAME,), {INPUT_NAME: features})[0]

    def frame_delta_k(self, features: np.ndarray) -> np.ndarray:
        """One frame's features (1, D), any float type -> Delta K (4,) float64 px: ``delta_k``
        through an ORT IO binding to float32 buffers made once per thread, which skips the
        per-call input and output conversions of ``session.run`` (the runtime's hot path)."""
        io = self._frame_io
        if not hasattr(io, "binding"):
            io.features, io.delta_k = np.empty((1, self.spec.features.size), np.float32), np.empty((1, 4), np.float32)
            io.binding = self.session.io_binding()
            io.binding.bind_cpu_input(INPUT_NAME, io.features)
            io.binding.bind_output(OUTPUT_NAME, "cpu", 0, np.float32, [1, 4], io.delta_k.ctypes.data)
        np.copyto(io.features, features)
        self.session.run_with_iobinding(io.binding)
        return io.delta_k[0].astype(np.float64)

    @property
    def providers(self) -> list:
        return self.session.get_providers()


def session_options(threads: int) -> ort.SessionOptions:
    """Sequential execution on ``threads`` intra-op threads (an int or a numpy integer; never a bool or a
    float), one inter-op thread, errors-only log; with more than one thread, the pool's threads sleep
    between calls instead of spinning (ONNX Runtime's advice where the caller does other work between
    calls, as the rectifier's PnP and features do: spinning threads take the cores they need)."""
    if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or not 1 <= threads <= MAX_THREADS:
        raise InputError(f"threads must be an integer from 1 to {MAX_THREADS} (4 x the CPUs), got {threads!r}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.log_severity_level = 3
    if threads > 1:
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return options


def _check_signature(session: ort.InferenceSession, spec: ModelSpec, source: str) -> None:
    """ModelError unless the graph maps float features [batch, spec.features.size] to delta_k [batch, 4]."""
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if [i.name for i in inputs] != [INPUT_NAME] or [o.name for o in outputs] != [OUTPUT_NAME]:
        raise ModelError(
            f"{source}: the graph must map input {INPUT_NAME!r} to output {OUTPUT_NAME!r}, "
            f"it maps {[i.name for i in inputs]} to {[o.name for o in outputs]}"
        )
    size = spec.features.size
    shape = inputs[0].shape
    if inputs[0].type != "tensor(float)" or len(shape) != 2 or shape[1] != size:
        raise ModelError(
            f"{source}: input {INPUT_NAME!r} is {inputs[0].type} {shape}, the spec's feature "
            f"({spec.features.variant}, grid {spec.features.grid}) needs tensor(float) [batch, {size}]"
        )
    if len(outputs[0].shape) != 2 or outputs[0].shape[1] != 4:
        raise ModelError(f"{source}: output {OUTPUT_NAME!r} has shape {outputs[0].shape}, expected [batch, 4]")


def _check_probe(session: ort.InferenceSession, spec: ModelSpec, source: str) -> None:
    """ModelError unless the graph really maps a zero feature batch (PROBE_FRAMES, D) to
    finite float32 (PROBE_FRAMES, 4): the declared signature is only what the file says."""
    declared = f"float32 [batch, 4] {OUTPUT_NAME!r}"
    zeros = np.zeros((PROBE_FRAMES, spec.features.size), np.float32)
    try:
        out = session.run((OUTPUT_NAME,), {INPUT_NAME: zeros})[0]
    except Exception as exc:  # ORT raises its own types when the graph cannot run
        raise ModelError(
            f"{source}: the graph fails on {PROBE_FRAMES} zero feature frames, so it differs from the declared "
            f"{declared} ({type(exc).__name__}: {str(exc).strip()[:300]})"
        ) from None
    if not isinstance(out, np.ndarray) or out.dtype != np.float32 or out.shape != (PROBE_FRAMES, 4):
        got = f"{out.dtype} {list(out.shape)}" if isinstance(out, np.ndarray) else type(out).__name__
        raise ModelError(
            f"{source}: graph output {OUTPUT_NAME!r} on {PROBE_FRAMES} zero feature frames is {got}, "
            f"it differs from the declared {declared}"
        )
    if not np.all(np.isfinite(out)):
        raise ModelError(f"{source}: graph output {OUTPUT_NAME!r} on zero features is not finite ({out[0].tolist()})")


_STAMP_KEY = b'"' + WEIGHTS_SHA256_KEY.encode("ascii") + b'"'
_STAMP_ENTRY = re.compile(re.escape(_STAMP_KEY) + rb'\s*:\s*"([0-9a-f]{64})"')
_PLACEHOLDER = WEIGHTS_SHA256_PLACEHOLDER.encode("ascii")


def weights_sha256_span(blob: bytes, digest: str) -> Optional[tuple]:
    """(start, end) of the 64 hex digits of the spec's ``"weights_sha256": "<digest>"`` entry in
    the file's bytes (JSON whitespace allowed around the colon), or None unless the key
    ``"weights_sha256"`` occurs exactly once in the bytes and holds ``digest`` there."""
    if blob.count(_STAMP_KEY) != 1:
        return None
    entry = _STAMP_ENTRY.match(blob, blob.rfind(_STAMP_KEY))
    return entry.span(1) if entry is not None and entry.group(1) == digest.encode("ascii") else None


def stamped_digests(blob: bytes, span: Optional[tuple]) -> Optional[tuple]:
    """(the sha256 of ``blob`` with the 64 hex digits at ``span`` set to the placeholder, 64 zeros;
    the sha256 of ``blob`` itself), in one pass over the bytes; None when ``span`` is (the stamp is
    ambiguous: ``weights_sha256_span``, ``ort_format.ort_sha256_span``). Export stamps a file with
    the first of its placeholder bytes (an ONNX file's ``weights_sha256``, an ORT-format file's
    ``ORT_SHA256_KEY``); the runtime checks it here."""
    if span is None:
        return None
    start, end = span
    view = memoryview(blob)
    stamped = hashlib.sha256(view[:start])
    whole = stamped.copy()
    stamped.update(_PLACEHOLDER)
    whole.update(view[start:end])
    stamped.update(view[end:])
    whole.update(view[end:])
    return stamped.hexdigest(), whole.hexdigest()


def _checked_sha256(blob: bytes, spec: ModelSpec, source: str) -> str:
    """The sha256 of an ONNX file's bytes, after checking them against the spec's ``weights_sha256``
    (spec >= 1.4; no check without it): ModelError when they differ."""
    if spec.weights_sha256 is None:
        return hashlib.sha256(blob).hexdigest()
    digests = stamped_digests(blob, weights_sha256_span(blob, spec.weights_sha256))
    if digests is None:
        raise ModelError(
            f"{source}: its spec's {WEIGHTS_SHA256_KEY} does not occur exactly once in the file's bytes: "
            f"corrupt or modified"
        )
    if digests[0] != spec.weights_sha256:
        raise ModelError(
            f"{source}: the model file's bytes differ from the sha256 in its spec: corrupt or modified "
            f"(sha256 {digests[0][:16]}..., spec {spec.weights_sha256[:16]}...)"
        )
    return digests[1]


def _checked_ort_sha256(blob: bytes, metadata: dict, source: str) -> str:
    """The sha256 of an ORT-format file's bytes, after checking them against its ``ORT_SHA256_KEY``,
    which it must have: ModelError when it has none or the bytes differ."""
    digest = metadata.get(ORT_SHA256_KEY)
    if digest is None:
        raise ModelError(
            f"{source}: an ORT-format model needs its {ORT_SHA256_KEY}, the hash that covers its graph: convert it "
            f"with `dimenet export MODEL.onnx --format ort` of this release"
        )
    digests = stamped_digests(blob, ort_sha256_span(blob, digest))
    if digests is None:
        raise ModelError(
            f"{source}: its {ORT_SHA256_KEY} does not occur exactly once in the file's bytes: corrupt or modified"
        )
    if digests[0] != digest:
        raise ModelError(
            f"{source}: the ORT-format file's bytes (graph, weights and spec) differ from its {ORT_SHA256_KEY}: "
            f"corrupt or modified (sha256 {digests[0][:16]}..., {ORT_SHA256_KEY} {digest[:16]}...)"
        )
    return digests[1]


def _check_content(text: str, tensors: list, spec: ModelSpec, source: str, *, required: bool) -> None:
    """ModelError unless the spec text and the tensors match the spec's content_sha256 (spec >= 1.9;
    no check without it, unless ``required``: an ORT-format file)."""
    if spec.content_sha256 is not None:
        found = content_sha256(text, tensors)
        if found != spec.content_sha256:
            raise ModelError(
                f"{source}: the model's spec and weights differ from the {CONTENT_SHA256_KEY} in its spec: corrupt "
                f"or modified (found {found[:16]}..., spec {spec.content_sha256[:16]}...)"
            )
    elif required:
        raise ModelError(
            f"{source}: an ORT-format model needs the {CONTENT_SHA256_KEY} of spec >= 1.9 to be checked: convert "
            f"it with `dimenet export MODEL.onnx --format ort` of this release"
        )


def onnx_model_from_bytes(
    blob: bytes, source: str, *, threads: int = 1, providers: Optional[Sequence[str]] = None
) -> OnnxModel:
    """Check the bytes hold only what the exporter writes (``check_model_bytes``; an ORT-format file:
    ``check_ort_bytes``), create the ORT session from them, read and validate its spec, check the
    graph's signature and a probe call against it, the spec and tensors against its content_sha256
    (spec >= 1.9; an ORT-format file must have one), an ONNX file's bytes against its weights_sha256 and
    an ORT-format file's against its ORT_SHA256_KEY (which it must have)."""
    options = session_options(threads)
    ort_format = is_ort_format(blob)
    tensors = check_ort_bytes(blob, source) if ort_format else check_model_bytes(blob, source)
    try:
        # On a failure ORT prints an "EP Error" banner to stdout and retries on its fallback
        # provider; the ModelError below is the one line a user gets.
        with contextlib.redirect_stdout(io.StringIO()):
            session = ort.InferenceSession(blob, options, providers=list(providers or DEFAULT_PROVIDERS))
    except Exception as exc:  # ORT raises its own exception types for corrupt files and bad providers
        kind = "ORT-format" if ort_format else "ONNX"
        raise ModelError(
            f"{source}: not a loadable {kind} model ({type(exc).__name__}: {str(exc).strip()[:300]})"
        ) from None
    try:
        metadata = session.get_modelmeta().custom_metadata_map
    except UnicodeDecodeError as exc:  # ONNX (proto2) strings are not checked to be UTF-8
        raise ModelError(f"{source}: the ONNX metadata is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    text = metadata.get(METADATA_KEY)
    if text is None:
        raise ModelError(
            f"{source}: no {METADATA_KEY!r} in the ONNX metadata: not a DIME-Net model "
            f"(export one with `dimenet export RUN_DIR --out model.onnx`)"
        )
    spec = ModelSpec.from_json(text, source=source)
    _check_signature(session, spec, source)
    _check_probe(session, spec, source)
    if ort_format:  # the spec and tensors (what the ONNX file shares), then the whole file
        _check_content(text, tensors, spec, source, required=True)
        sha256 = _checked_ort_sha256(blob, metadata, source)
    else:  # the whole file, then the spec and tensors
        sha256 = _checked_sha256(blob, spec, source)
        _check_content(text, tensors, spec, source, required=False)
    model = OnnxModel(session=session, spec=spec, source=source, sha256=sha256)
    model.frame_delta_k(np.zeros((1, spec.features.size)))  # warm-up: the first frame's call pays no set-up
    return model


def load_onnx_model(path: str | Path, *, threads: int = 1, providers: Optional[Sequence[str]] = None) -> OnnxModel:
    """Load a ``dimenet-model/1`` .onnx file (see ``onnx_model_from_bytes``)."""
    path = Path(path)
    if path.is_dir():
        raise ModelError(
            f"{path}: a folder, the runtime needs a .onnx file (`dimenet export RUN_DIR --out model.onnx`)"
        )
    if not path.is_file():
        raise ModelError(f"{path}: no such model file")
    return onnx_model_from_bytes(read_model_file(path), str(path), threads=threads, providers=providers)


def read_model_file(path: Path) -> bytes:
    """The bytes of a model file, reading at most MAX_MODEL_BYTES + 1: ModelError naming the file
    when it cannot be read or is larger."""
    try:
        with path.open("rb") as f:
            blob = f.read(MAX_MODEL_BYTES + 1)
    except OSError as exc:
        raise ModelError(f"{path}: cannot read the model file ({exc.strerror or exc})") from None
    if len(blob) > MAX_MODEL_BYTES:
        raise ModelError(f"{path}: larger than {MAX_MODEL_BYTES} bytes, too large for a DIME-Net model")
    return blob


@dataclass(frozen=True)
class ModelRef:
    """A model named where one is taken: a bundled model (``bundled``, a key of BUNDLED_MODELS) or an existing
    ``path`` (a model file, or a RUN_DIR that the training's loaders read)."""

    bundled: Optional[str] = None
    path: Optional[Path] = None

    @property
    def source(self) -> str:
        """How errors and reports name the model."""
        return bundled_source(self.bundled) if self.bundled is not None else str(self.path)

    @property
    def run_dir(self) -> bool:
        """A folder (a RUN_DIR of `dimenet train`), not a model file nor a bundled model."""
        return self.path is not None and self.path.is_dir()

    def model_bytes(self) -> bytes:
        """The model file's bytes (``bundled_model_bytes``, ``read_model_file``); a RUN_DIR has none."""
        return bundled_model_bytes(self.bundled) if self.bundled is not None else read_model_file(self.path)


def resolve_model(model: Optional[str | Path] = None) -> ModelRef:
    """The one reading of a model argument: None is the default bundled model, a name in BUNDLED_MODELS that
    bundled model ("./default": a file of that name), anything else a path that must exist (ModelError naming
    the bundled models otherwise)."""
    name = DEFAULT_NAME if model is None else str(model)
    if name in BUNDLED_MODELS:
        return ModelRef(bundled=name)
    path = Path(model)
    if not path.exists():
        raise ModelError(
            f"{path}: no such model file or RUN_DIR, nor a bundled model's name ({', '.join(BUNDLED_MODELS)})"
        )
    return ModelRef(path=path)


def load_model(path: Optional[str | Path] = None, *, threads: int = 1, providers=None) -> OnnxModel:
    """A ``dimenet-model/1`` .onnx file, or a bundled model (``resolve_model``), ModelError when this
    installation lacks it."""
    ref = resolve_model(path)
    if ref.bundled is None:
        return load_onnx_model(ref.path, threads=threads, providers=providers)
    return onnx_model_from_bytes(ref.model_bytes(), ref.source, threads=threads, providers=providers)


def bundled_source(name: str) -> str:
    """How errors and reports name the bundled model ``name`` (a key of BUNDLED_MODELS)."""
    return f"bundled {name} model ({BUNDLED_MODELS[name]})"


def bundled_model_bytes(name: str = DEFAULT_NAME) -> bytes:
    """The file of the bundled model ``name`` (a key of BUNDLED_MODELS), or ModelError when this
    installation has none."""
    resource = asset(BUNDLED_MODELS[name])
    if not resource.is_file():
        raise ModelError(
            f"this installation has no bundled {name} model (dimenet/runtime/assets/{BUNDLED_MODELS[name]}); "
            f"pass a model file from `dimenet export`"
        )
    return resource.read_bytes()
