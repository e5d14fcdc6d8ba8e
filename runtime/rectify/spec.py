"""Model spec ``dimenet-model/1``: everything needed to turn correspondences into the
network input and its output into K. Written by training (RUN_DIR/spec.json), embedded by
export into the ONNX ``metadata_props`` under the key ``dimenet_model_spec``, read by the
runtime. See models_spec/model-v1.md.

``from_dict`` trusts nothing: every field is checked for type, shape, finiteness and range,
and any problem is a ModelError naming the source and the field (never a traceback, and
never a spec that loads and then fails or falls back on every frame).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from dimenet.runtime.errors import ModelError
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.json_text import JsonProblem, integer, numbers, parse_json, required, shown
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.uncertainty import PARAMETERS, Uncertainty

FORMAT = "dimenet-model/1"
# semver of the spec; a reader refuses another major version and reads every 1.x (the minor
# versions and what each added: models_spec/model-v1.md).
VERSION = "1.4.0"
METADATA_KEY = "dimenet_model_spec"
# Spec >= 1.4, optional: the sha256 of the model file's bytes with this value replaced by
# WEIGHTS_SHA256_PLACEHOLDER (model-v1.md, "Integrity"; written by export, checked by the runtime).
WEIGHTS_SHA256_KEY = "weights_sha256"
WEIGHTS_SHA256_PLACEHOLDER = "0" * 64
MAX_IMAGE_SIDE_PX = 100_000
MAX_SPEC_CHARS = 4 << 20  # a spec is a few KiB
_HEX64 = re.compile(r"[0-9a-f]{64}")


def _checked(d: dict) -> dict:
    """The ModelSpec fields of a spec dict, every one checked (``JsonProblem`` names the field)."""
    k_c = numbers(required(d, "K_c"), (4,), "K_c")
    if not (k_c[0] > 0 and k_c[1] > 0):
        raise JsonProblem(f"K_c must have fx, fy > 0, got {k_c.tolist()}")
    size = required(d, "image_size")
    if not isinstance(size, list) or len(size) != 2:
        raise JsonProblem(f"image_size must be 2 integers (width, height), got {shown(size)}")
    image_size = tuple(integer(v, "image_size", 1, MAX_IMAGE_SIDE_PX) for v in size)
    bounds = numbers(required(d, "K_bounds"), (4, 2), "K_bounds")
    for p, name in enumerate(PARAMETERS):
        low, high = bounds[p]
        if not low < high:
            raise JsonProblem(f"K_bounds of {name} must have low < high, got [{low}, {high}]")
        if not low <= k_c[p] <= high:
            raise JsonProblem(f"K_bounds of {name} [{low}, {high}] must contain K_c's {name} {k_c[p]}")
    hidden = required(d, "hidden")
    if not isinstance(hidden, list) or not hidden:
        raise JsonProblem(f"hidden must be a list of layer widths, got {shown(hidden)}")
    features = FeatureSpec.from_dict(required(d, "features"), image_size)
    provenance = d.get("provenance", {})
    if not isinstance(provenance, dict):
        raise JsonProblem(f"provenance must be an object, got {shown(provenance)}")
    weights_sha256 = d.get(WEIGHTS_SHA256_KEY)
    if weights_sha256 is not None and not (isinstance(weights_sha256, str) and _HEX64.fullmatch(weights_sha256)):
        raise JsonProblem(f"{WEIGHTS_SHA256_KEY} must be 64 lowercase hex digits, got {shown(weights_sha256)}")
    return {
        "features": features,
        "K_c": k_matrix(k_c),
        "image_size": image_size,
        "K_bounds": bounds,
        "hidden": tuple(integer(h, "hidden", 1) for h in hidden),
        "provenance": dict(provenance),
        "uncertainty": Uncertainty.from_dict(d["uncertainty"], features.grid.n_cells) if "uncertainty" in d else None,
        "weights_sha256": weights_sha256,
    }


@dataclass(frozen=True)
class ModelSpec:
    """features: the grid feature; K_c (3, 3) px; image_size (width, height) px; K_bounds: per
    parameter (fx, fy, cx, cy) the [low, high] px range of plausible K (outside it, the runtime
    falls back to K_c); uncertainty: the model of the network's Delta K covariance (None in
    1.0 specs); provenance: dataset sha256, seed, versions, command; weights_sha256: the
    integrity hash the model file's spec declared (None for a spec on its own or before 1.4).
    It belongs to one file, so ``to_dict`` leaves it out unless given one (export stamps it)."""

    features: FeatureSpec
    K_c: np.ndarray
    image_size: tuple
    K_bounds: np.ndarray  # (4, 2) px
    hidden: tuple
    provenance: dict = field(default_factory=dict)
    uncertainty: Optional[Uncertainty] = None
    weights_sha256: Optional[str] = field(default=None, compare=False)

    def to_dict(self, *, weights_sha256: Optional[str] = None) -> dict:
        d = {
            "format": FORMAT,
            "version": VERSION,
            "features": self.features.to_dict(),
            "K_c": k_params(self.K_c).tolist(),
            "image_size": [int(v) for v in self.image_size],
            "K_bounds": np.asarray(self.K_bounds).tolist(),
            "hidden": list(self.hidden),
            "provenance": self.provenance,
        }
        if self.uncertainty is not None:
            d["uncertainty"] = self.uncertainty.to_dict()
        if weights_sha256 is not None:
            d[WEIGHTS_SHA256_KEY] = weights_sha256
        return d

    def to_json(self, *, weights_sha256: Optional[str] = None) -> str:
        return json.dumps(self.to_dict(weights_sha256=weights_sha256), indent=1, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "model") -> ModelSpec:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            found = shown(d.get("format")) if isinstance(d, dict) else f"a JSON {type(d).__name__}"
            raise ModelError(f"{source}: not a {FORMAT} spec (format is {found})")
        version = d.get("version")
        if not isinstance(version, str) or version.split(".")[0] != VERSION.split(".")[0]:
            raise ModelError(
                f"{source}: spec version {shown(version)} is not supported "
                f"(this runtime reads {VERSION.split('.')[0]}.x)"
            )
        try:
            return cls(**_checked(d))
        except ValueError as exc:  # JsonProblem, and the parts' own checks (FeatureSpec, Uncertainty)
            raise ModelError(f"{source}: malformed {FORMAT} spec: {exc}") from None

    @classmethod
    def from_json(cls, text: str, *, source: str = "model") -> ModelSpec:
        try:
            d = parse_json(text, max_chars=MAX_SPEC_CHARS)
        except JsonProblem as exc:
            raise ModelError(f"{source}: spec is not valid JSON ({exc})") from None
        return cls.from_dict(d, source=source)

    @classmethod
    def read(cls, path: str | Path) -> ModelSpec:
        path = Path(path)
        if not path.is_file():
            raise ModelError(f"{path}: no model spec file")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise ModelError(f"{path}: model spec is not UTF-8 text") from None
        return cls.from_json(text, source=str(path))

    def map_uncertainty(self, source: str) -> Uncertainty:
        """The uncertainty model that MAP rectification needs, or ModelError naming ``source``."""
        if self.uncertainty is None:
            raise ModelError(
                f"{source}: its spec has no uncertainty model (spec 1.0), which mode 'map' needs: "
                f"re-export a model trained by this release"
            )
        return self.uncertainty

    def k_within_bounds(self, k: np.ndarray) -> np.ndarray:
        """The K-bounds rule: k (..., 4) px (fx, fy, cx, cy) -> (...,) bool, every parameter inside
        [low, high] of K_bounds. A NaN fails it, so a non-finite K is refused too."""
        return np.all((k >= self.K_bounds[:, 0]) & (k <= self.K_bounds[:, 1]), axis=-1)
