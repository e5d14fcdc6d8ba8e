"""The renderer's truth (``truth.npz``, see models_spec/ingest.md): per rendered photo its K, pose and every
rig corner's true pixel, read without pickle (``read_truth``). Written by ``sim.render``; an ingested dataset
is scored against it by ``bench.ingest_score``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.formats.dataset import LENS_KEYS, MAX_META_CHARS
from dimenet.runtime.formats.npz import read_npz
from dimenet.runtime.json_text import JsonProblem, parse_json


@dataclass(frozen=True)
class Truth:
    """Per photo: file name (N,), K (N, 3, 3) px, pose {W}->{C} (N, 3) rad / mm, every rig corner's true
    pixel (N, P, 2) and whether its board is shown whole (N, P); the rig's board of each corner (P,);
    the lens the photos were taken through (dist_coeffs (n,) about dist_K (3, 3) px), or None; meta: how they
    were rendered (``sim.render``'s seed, profile, ...; {} for a file without it)."""

    frame_id: np.ndarray
    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    corners_px: np.ndarray
    seen: np.ndarray
    board_of_point: np.ndarray
    upside_down: np.ndarray  # (N,) bool
    covered_board: np.ndarray  # (N,) int, -1 for none
    dist_coeffs: Optional[np.ndarray] = None
    dist_K: Optional[np.ndarray] = None
    meta: dict = field(default_factory=dict)


def _truth_array(arrays: dict, key: str, kinds: str, shape: tuple, named: str) -> np.ndarray:
    """``arrays[key]`` if its dtype kind is one of ``kinds`` and its shape is ``shape`` (``named``: as the spec
    writes it); floats as float64."""
    a = arrays[key]
    if a.dtype.kind not in kinds or a.shape != shape:
        kind = {"f": "a float", "b": "a bool", "iu": "an integer", "U": "a string"}[kinds]
        raise DatasetError(f"{key}: must be {kind} array of shape {named}, got {a.dtype} {a.shape}")
    return a.astype(np.float64, copy=False) if kinds == "f" else a


def read_truth(path: str | Path) -> Truth:
    """Read a renderer's truth.npz (never pickle-loads). Raises DatasetError naming the file: also for a
    corrupt, truncated or oversized archive (refused before decoding) and for arrays of the wrong shape."""
    arrays = read_npz(path, DatasetError, "render truth file")
    missing = [k for k in Truth.__dataclass_fields__ if k not in arrays and k not in LENS_KEYS]
    if missing:
        raise DatasetError(f"{path}: not a render truth file (missing {missing[0]!r})")
    try:
        frame_id = arrays["frame_id"]
        N = frame_id.shape[0] if frame_id.ndim == 1 else -1
        P = arrays["board_of_point"].shape[0] if arrays["board_of_point"].ndim == 1 else -1
        lens = {}
        if any(k in arrays for k in LENS_KEYS):
            if not all(k in arrays for k in LENS_KEYS):
                raise DatasetError(f"{LENS_KEYS[0]} and {LENS_KEYS[1]}: give both or neither")
            n = arrays["dist_coeffs"].shape[0] if arrays["dist_coeffs"].ndim == 1 else -1
            lens = {
                "dist_coeffs": _truth_array(arrays, "dist_coeffs", "f", (n,), "(n,)"),
                "dist_K": _truth_array(arrays, "dist_K", "f", (3, 3), "(3, 3)"),
            }
        try:
            meta = parse_json(str(arrays["meta"]), max_chars=MAX_META_CHARS) if "meta" in arrays else {}
        except JsonProblem as exc:
            raise DatasetError(f"meta: {exc}") from None
        if not isinstance(meta, dict):
            raise DatasetError("meta: must be a JSON object")
        return Truth(
            frame_id=_truth_array(arrays, "frame_id", "U", (N,), "(N,)"),
            K=_truth_array(arrays, "K", "f", (N, 3, 3), "(N, 3, 3)"),
            rvec=_truth_array(arrays, "rvec", "f", (N, 3), "(N, 3)"),
            tvec=_truth_array(arrays, "tvec", "f", (N, 3), "(N, 3)"),
            corners_px=_truth_array(arrays, "corners_px", "f", (N, P, 2), "(N, P, 2)"),
            seen=_truth_array(arrays, "seen", "b", (N, P), "(N, P)"),
            board_of_point=_truth_array(arrays, "board_of_point", "iu", (P,), "(P,)"),
            upside_down=_truth_array(arrays, "upside_down", "b", (N,), "(N,)"),
            covered_board=_truth_array(arrays, "covered_board", "iu", (N,), "(N,)"),
            **lens,
            meta=meta,
        )
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None
