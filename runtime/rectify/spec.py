"""Model spec ``dimenet-model/1``: everything needed to turn correspondences into the
network input and its output into K. Written by training (RUN_DIR/spec.json), embedded by
export into the ONNX ``metadata_props`` under the key ``dimenet_model_spec``, read by the
runtime. See models_spec/model-v1.md.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from dimenet.runtime.errors import ModelError
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.uncertainty import Uncertainty

FORMAT = "dimenet-model/1"
# semver of the spec; a reader refuses another major version and reads every 1.x (the minor
# versions and what each added: models_spec/model-v1.md).
VERSION = "1.3.0"
METADATA_KEY = "dimenet_model_spec"


@dataclass(frozen=True)
class ModelSpec:
    """features: the grid feature; K_c (3, 3) px; image_size (width, height) px; K_bounds: per
    parameter (fx, fy, cx, cy) the [low, high] px range of plausible K (outside it, the runtime
    falls back to K_c); uncertainty: the model of the network's Delta K covariance (None in
    1.0 specs); provenance: dataset sha256, seed, versions, command."""

    features: FeatureSpec
    K_c: np.ndarray
    image_size: tuple
    K_bounds: np.ndarray  # (4, 2) px
    hidden: tuple
    provenance: dict = field(default_factory=dict)
    uncertainty: Optional[Uncertainty] = None

    def to_dict(self) -> dict:
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
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "model") -> ModelSpec:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ModelError(
                f"{source}: not a {FORMAT} spec (format is {d.get('format') if isinstance(d, dict) else d!r})"
            )
        major = str(d.get("version", "")).split(".")[0]
        if major != VERSION.split(".")[0]:
            raise ModelError(
                f"{source}: spec version {d.get('version')!r} is not supported "
                f"(this runtime reads {VERSION.split('.')[0]}.x)"
            )
        try:
            return cls(
                features=FeatureSpec.from_dict(d["features"]),
                K_c=k_matrix(np.asarray(d["K_c"], float)),
                image_size=tuple(int(v) for v in d["image_size"]),
                K_bounds=np.asarray(d["K_bounds"], float),
                hidden=tuple(int(h) for h in d["hidden"]),
                provenance=dict(d.get("provenance", {})),
                uncertainty=Uncertainty.from_dict(d["uncertainty"]) if "uncertainty" in d else None,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"{source}: malformed {FORMAT} spec ({type(exc).__name__}: {exc})") from None

    @classmethod
    def from_json(cls, text: str, *, source: str = "model") -> ModelSpec:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelError(f"{source}: spec is not valid JSON ({exc.msg})") from None
        return cls.from_dict(d, source=source)

    @classmethod
    def read(cls, path: str | Path) -> ModelSpec:
        path = Path(path)
        if not path.is_file():
            raise ModelError(f"{path}: no model spec file")
        return cls.from_json(path.read_text(encoding="utf-8"), source=str(path))

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
