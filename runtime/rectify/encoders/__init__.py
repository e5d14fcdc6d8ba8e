"""The registry of the feature's encoders: one module each (its size, numpy reference and which part of the
compiled core's ``dimenet_frame_features`` output it is), in the order their inputs follow each other.

Every module has NAME, ``size(spec)`` (0 when the spec does not use it) and ``encode``: the grid's, first, from the
point rows; each one after it per frame from the frame's monomial Gram (``encode(G, n, K_c, spec)``). Their ONNX
subgraph builders live on the export side (``export.full_graph``), keyed by these names, so the runtime needs no
onnx.
"""

from __future__ import annotations

from dimenet.runtime.rectify.encoders import data_step, grid, moments

ENCODERS = {module.NAME: module for module in (grid, data_step, moments)}


def spans(spec) -> dict:
    """Encoder name -> slice of the feature its inputs fill under ``spec`` (empty when it has none)."""
    out, start = {}, 0
    for name, module in ENCODERS.items():
        stop = start + module.size(spec)
        out[name] = slice(start, stop)
        start = stop
    return out
