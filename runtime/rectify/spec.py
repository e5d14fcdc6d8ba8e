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
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from dimenet.runtime.errors import ModelError
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.rectify.features import CHANNELS, FeatureSpec
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.uncertainty import D_FLOOR_PX, NOISE_SCALE_PX, PARAMETERS, STATISTICS, T_FLOOR, Uncertainty

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
# The uncertainty model must keep every sigma within [SIGMA_MIN_PX, SIGMA_MAX_PX] over the
# box of plausible frame statistics: n in [1, MAX_POINTS] points, m in [1, the grid's cells]
# occupied cells, PMD d in [D_FLOOR_PX, MAX_PMD_PX] px, thickness t in [T_FLOOR, 1/3].
MAX_POINTS = 100_000
MAX_PMD_PX = 1_000.0
SIGMA_MIN_PX, SIGMA_MAX_PX = 1e-6, 1e6
_HEX64 = re.compile(r"[0-9a-f]{64}")


class _Malformed(Exception):
    """One field's problem; ``from_dict`` turns it into a ModelError naming the source."""


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(value: Any) -> bool:
    """A finite JSON number (a float, or an int a float holds; never a bool or a string)."""
    kind = type(value)
    if kind is float:
        return math.isfinite(value)
    return kind is int and -1e300 <= value <= 1e300


def _numbers(value: Any, shape: tuple, name: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` (one or two axes): nested JSON lists of finite
    numbers, exactly (no strings, no booleans, no ragged lists)."""
    rows, n_rows = (value, shape[0]) if len(shape) == 2 else ([value], 1)
    if not isinstance(rows, list) or len(rows) != n_rows:
        raise _Malformed(f"{name} must be {' x '.join(map(str, shape))} numbers, got {_show(value)}")
    for row in rows:
        if not isinstance(row, list) or len(row) != shape[-1]:
            raise _Malformed(f"{name} must be {' x '.join(map(str, shape))} numbers, got {_show(value)}")
        for v in row:
            if not _is_number(v):
                raise _Malformed(f"{name} must hold finite numbers, got {_show(v)}")
    return np.array(value, dtype=np.float64)


def _integer(value: Any, name: str, low: int, high: Optional[int] = None) -> int:
    """An integer (an integral JSON number) in [low, high]."""
    if not _is_number(value) or value != int(value):
        raise _Malformed(f"{name} must be an integer, got {_show(value)}")
    if value < low or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"{low} to {high}"
        raise _Malformed(f"{name} must be {bound}, got {_show(value)}")
    return int(value)


def _required(d: dict, key: str) -> Any:
    if key not in d:
        raise _Malformed(f"no {key!r}")
    return d[key]


def _features(d: Any, image_size: tuple) -> FeatureSpec:
    if not isinstance(d, dict):
        raise _Malformed(f"features must be an object, got {_show(d)}")
    grid_text, variant, scale = _required(d, "grid"), _required(d, "variant"), _required(d, "scale")
    if not isinstance(grid_text, str):
        raise _Malformed(f"features.grid must be a string like '8x6', got {_show(grid_text)}")
    try:
        grid = Grid.parse(grid_text)
    except ValueError as exc:
        raise _Malformed(f"features.{exc}") from None
    if grid.cols > image_size[0] or grid.rows > image_size[1]:
        raise _Malformed(
            f"features.grid {grid} has more cells than the {image_size[0]}x{image_size[1]} image has pixels"
        )
    if not isinstance(variant, str):
        raise _Malformed(f"features.variant must be a string, got {_show(variant)}")
    if not isinstance(scale, dict):
        raise _Malformed(f"features.scale must be an object, got {_show(scale)}")
    unknown = [key for key in scale if key not in CHANNELS]
    if unknown:
        raise _Malformed(f"features.scale has an unknown channel {unknown[0]!r} (channels: {', '.join(CHANNELS)})")
    for channel in CHANNELS:
        value = scale.get(channel)
        if not (_is_number(value) and value > 0):
            raise _Malformed(f"features.scale.{channel} must be a positive number, got {_show(value)}")
    try:
        return FeatureSpec(grid=grid, variant=variant, scale={c: float(scale[c]) for c in CHANNELS})
    except ValueError as exc:
        raise _Malformed(f"features: {exc}") from None


def _log_sigma_range(coef: np.ndarray, statistics: tuple, n_cells: int) -> tuple:
    """(4,) lowest and highest log sigma of each parameter over the box of plausible statistics
    (``MAX_POINTS``, ...): coef . z is linear, so its extremes are at the box's corners."""
    box = {
        "log_points": (0.0, math.log(MAX_POINTS)),
        "log_cells": (0.0, math.log(n_cells)),
        "log_pmd": (math.log(D_FLOOR_PX), math.log(MAX_PMD_PX)),
        "log_thickness": (math.log(T_FLOOR), math.log(1 / 3)),
    }
    low, high = coef[:, 0].copy(), coef[:, 0].copy()
    with np.errstate(over="ignore", invalid="ignore"):  # absurd coefficients give +-inf or NaN: refused
        for column, name in enumerate(statistics, start=1):
            ends = np.outer(coef[:, column], box[name])  # (4, 2)
            low += ends.min(1)
            high += ends.max(1)
    return low, high


def _exp(x: float) -> str:
    """exp(x) for a message, also where it overflows a float."""
    return f"{math.exp(x):.3g}" if x < 700 else f"exp({x:.3g})"


def _uncertainty(d: Any, n_cells: int) -> Uncertainty:
    if not isinstance(d, dict):
        raise _Malformed(f"uncertainty must be an object, got {_show(d)}")
    if d.get("parameters", list(PARAMETERS)) != list(PARAMETERS):
        raise _Malformed(f"uncertainty.parameters must be {list(PARAMETERS)}, got {_show(d['parameters'])}")
    names = d.get("statistics", ["1", *STATISTICS[:3]])  # 1.1 files: the first three
    if (
        not isinstance(names, list)
        or not names
        or names[0] != "1"
        or not all(isinstance(n, str) and n in STATISTICS for n in names[1:])
        or len(set(names[1:])) != len(names) - 1
    ):
        raise _Malformed(
            f"uncertainty.statistics must be '1' then distinct names among {list(STATISTICS)}, got {_show(names)}"
        )
    statistics = tuple(names[1:])
    coef = _numbers(_required(d, "coef"), (4, len(names)), "uncertainty.coef")
    correlation = _numbers(_required(d, "correlation"), (4, 4), "uncertainty.correlation")
    if not (np.abs(correlation - correlation.T).max() <= 1e-9 and np.abs(np.diag(correlation) - 1).max() <= 1e-6):
        raise _Malformed("uncertainty.correlation must be a symmetric matrix with a unit diagonal")
    rho = _numbers(d.get("data_correlation", [0.0] * 4), (4,), "uncertainty.data_correlation")
    s0 = d.get("noise_scale_px", NOISE_SCALE_PX)
    if not (_is_number(s0) and s0 > 0):
        raise _Malformed(f"uncertainty.noise_scale_px must be a positive number, got {_show(s0)}")
    low, high = _log_sigma_range(coef, statistics, n_cells)
    for p, name in enumerate(PARAMETERS):
        if not math.log(SIGMA_MIN_PX) <= low[p] <= high[p] <= math.log(SIGMA_MAX_PX):
            raise _Malformed(
                f"uncertainty.coef gives sigma_{name} from {_exp(low[p])} to {_exp(high[p])} px over "
                f"plausible frames (n <= {MAX_POINTS} points, m <= {n_cells} cells, PMD {D_FLOOR_PX} to {MAX_PMD_PX:g} "
                f"px, thickness {T_FLOOR:g} to 1/3), outside [{SIGMA_MIN_PX:g}, {SIGMA_MAX_PX:g}] px"
            )
    try:
        return Uncertainty(
            coef=coef, correlation=correlation, statistics=statistics, data_correlation=rho, noise_scale_px=float(s0)
        )
    except ValueError as exc:
        raise _Malformed(str(exc)) from None


def _checked(d: dict) -> dict:
    """The ModelSpec fields of a spec dict, every one checked (``_Malformed`` names the field)."""
    k_c = _numbers(_required(d, "K_c"), (4,), "K_c")
    if not (k_c[0] > 0 and k_c[1] > 0):
        raise _Malformed(f"K_c must have fx, fy > 0, got {k_c.tolist()}")
    size = _required(d, "image_size")
    if not isinstance(size, list) or len(size) != 2:
        raise _Malformed(f"image_size must be 2 integers (width, height), got {_show(size)}")
    image_size = tuple(_integer(v, "image_size", 1, MAX_IMAGE_SIDE_PX) for v in size)
    bounds = _numbers(_required(d, "K_bounds"), (4, 2), "K_bounds")
    for p, name in enumerate(PARAMETERS):
        low, high = bounds[p]
        if not low < high:
            raise _Malformed(f"K_bounds of {name} must have low < high, got [{low}, {high}]")
        if not low <= k_c[p] <= high:
            raise _Malformed(f"K_bounds of {name} [{low}, {high}] must contain K_c's {name} {k_c[p]}")
    hidden = _required(d, "hidden")
    if not isinstance(hidden, list) or not hidden:
        raise _Malformed(f"hidden must be a list of layer widths, got {_show(hidden)}")
    features = _features(_required(d, "features"), image_size)
    provenance = d.get("provenance", {})
    if not isinstance(provenance, dict):
        raise _Malformed(f"provenance must be an object, got {_show(provenance)}")
    weights_sha256 = d.get(WEIGHTS_SHA256_KEY)
    if weights_sha256 is not None and not (isinstance(weights_sha256, str) and _HEX64.fullmatch(weights_sha256)):
        raise _Malformed(f"{WEIGHTS_SHA256_KEY} must be 64 lowercase hex digits, got {_show(weights_sha256)}")
    return {
        "features": features,
        "K_c": k_matrix(k_c),
        "image_size": image_size,
        "K_bounds": bounds,
        "hidden": tuple(_integer(h, "hidden", 1) for h in hidden),
        "provenance": dict(provenance),
        "uncertainty": _uncertainty(d["uncertainty"], features.grid.n_cells) if "uncertainty" in d else None,
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
            shown = _show(d.get("format")) if isinstance(d, dict) else f"a JSON {type(d).__name__}"
            raise ModelError(f"{source}: not a {FORMAT} spec (format is {shown})")
        version = d.get("version")
        if not isinstance(version, str) or version.split(".")[0] != VERSION.split(".")[0]:
            raise ModelError(
                f"{source}: spec version {_show(version)} is not supported "
                f"(this runtime reads {VERSION.split('.')[0]}.x)"
            )
        try:
            return cls(**_checked(d))
        except _Malformed as exc:
            raise ModelError(f"{source}: malformed {FORMAT} spec: {exc}") from None

    @classmethod
    def from_json(cls, text: str, *, source: str = "model") -> ModelSpec:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelError(f"{source}: spec is not valid JSON ({exc.msg})") from None
        except ValueError as exc:  # e.g. an integer of more digits than Python converts
            raise ModelError(f"{source}: spec is not valid JSON ({exc})") from None
        except RecursionError:
            raise ModelError(f"{source}: spec JSON is nested too deeply") from None
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
