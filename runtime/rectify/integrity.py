"""The content hash of a model (spec >= 1.9, ``content_sha256``): the sha256 of its spec and its
constant tensors, so it holds across file formats (an ONNX file and its ORT-format conversion
hold the same spec text and tensors, not the same bytes). models_spec/model-v1.md, "Integrity".

digest = sha256(b"dimenet-content/1\\0" + the spec JSON text with the values of ``weights_sha256``
and ``content_sha256`` set to 64 zeros + for each tensor in name order: its name (UTF-8), a NUL,
the count of its dims and the dims (int64 little-endian), the count of its bytes (int64) and its
float32 values (little-endian)).
"""

from __future__ import annotations

import hashlib
import re
import struct

from dimenet.runtime.rectify.spec import CONTENT_SHA256_KEY, WEIGHTS_SHA256_KEY, WEIGHTS_SHA256_PLACEHOLDER

DOMAIN = b"dimenet-content/1\0"
_DIGEST_ENTRY = re.compile(rf'("(?:{WEIGHTS_SHA256_KEY}|{CONTENT_SHA256_KEY})"\s*:\s*")[0-9a-f]{{64}}(")')


def zeroed_spec_text(text: str) -> str:
    """The spec JSON text with the values of its digests set to 64 zeros."""
    return _DIGEST_ENTRY.sub(lambda m: m.group(1) + WEIGHTS_SHA256_PLACEHOLDER + m.group(2), text)


def content_sha256(spec_text: str, tensors: list) -> str:
    """The content digest (module doc) of a spec's JSON text and a model's constant tensors
    (``onnx_graph.Tensor``: name, dims, little-endian float32 bytes)."""
    h = hashlib.sha256(DOMAIN)
    h.update(zeroed_spec_text(spec_text).encode("utf-8"))
    for t in sorted(tensors, key=lambda t: t.name):
        h.update(t.name.encode("utf-8") + b"\0")
        h.update(struct.pack(f"<q{len(t.dims)}q", len(t.dims), *t.dims))
        h.update(struct.pack("<q", len(t.data)))
        h.update(t.data)
    return h.hexdigest()
