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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional

import numpy as np

from dimenet.runtime.errors import CameraError, ModelError
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.json_text import JsonProblem, integer, is_number, numbers, parse_json, required, shown
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.uncertainty import PARAMETERS, Uncertainty
from dimenet.runtime.rectify.user_camera import MAX_IMAGE_SIDE_PX, Camera, PixelMap, device_pixel_map, generic_pixel_map

FORMAT = "dimenet-model/1"
# semver of the spec; a reader refuses another major version and reads every 1.x (the minor
# versions and what each added: models_spec/model-v1.md).
VERSION = "1.11.0"
METADATA_KEY = "dimenet_model_spec"
# Spec >= 1.4, optional: the sha256 of the model file's bytes with this value replaced by
# WEIGHTS_SHA256_PLACEHOLDER (model-v1.md, "Integrity"; written by export, checked by the runtime).
WEIGHTS_SHA256_KEY = "weights_sha256"
# Spec >= 1.9, optional: the sha256 of the spec and the constant tensors (rectify.integrity), which an
# ORT-format conversion keeps; written by export with WEIGHTS_SHA256_PLACEHOLDER's zeros first.
CONTENT_SHA256_KEY = "content_sha256"
WEIGHTS_SHA256_PLACEHOLDER = "0" * 64
# The network's output head (spec >= 1.8; absent: "mlp", the paper's): "gated_step" adds the
# feature's data step through a learned gate (training.model; models_spec/model-v1.md).
HEADS = ("mlp", "gated_step")


def head_problem(head: Any, data_step: bool, step_name: str) -> Optional[str]:
    """Why a network of output ``head`` cannot sit on a feature with (``data_step``) or without the
    data step, named ``step_name`` where the caller sets it; None when it can."""
    if head not in HEADS:
        return f"head must be one of {', '.join(HEADS)}, got {shown(head)}"
    if head == "gated_step" and not data_step:
        return f"head gated_step needs {step_name} (the data step it gates)"
    return None


MAX_SPEC_CHARS = 4 << 20  # a spec is a few KiB
_HEX64 = re.compile(r"[0-9a-f]{64}")


def _checked_generic(d: dict) -> dict:
    """The camera fields of a generic spec (>= 1.5): ``generic`` {focal_px, delta_bounds}, and
    no K_c, image_size or K_bounds of its own."""
    for key in ("K_c", "image_size", "K_bounds"):
        if key in d:
            raise JsonProblem(f"a generic model has no {key} of its own (the camera is given at run time)")
    g = d["generic"]
    if not isinstance(g, dict):
        raise JsonProblem(f"generic must be an object, got {shown(g)}")
    focal = required(g, "focal_px")
    if not (is_number(focal) and 1.0 <= focal <= MAX_IMAGE_SIDE_PX):
        raise JsonProblem(f"generic.focal_px must be a number in [1, {MAX_IMAGE_SIDE_PX}], got {shown(focal)}")
    bounds = numbers(required(g, "delta_bounds"), (4, 2), "generic.delta_bounds")
    for p, name in enumerate(PARAMETERS):
        low, high = bounds[p]
        if not low <= 0.0 <= high or not low < high:
            raise JsonProblem(
                f"generic.delta_bounds of {name} must have low <= 0 <= high and low < high, got [{low}, {high}]"
            )
    features = FeatureSpec.from_dict(required(d, "features"))
    if features.depth_mm is None:
        raise JsonProblem("a generic model's features need depth_mm (the scale-free depth)")
    generic = GenericCamera(focal_px=float(focal), delta_bounds=bounds)
    return {"features": features, "K_c": None, "image_size": None, "K_bounds": None, "generic": generic}


def _checked_camera(d: dict) -> dict:
    """The camera fields of a device spec: K_c, image_size, K_bounds."""
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
    features = FeatureSpec.from_dict(required(d, "features"), image_size)
    return {"features": features, "K_c": k_matrix(k_c), "image_size": image_size, "K_bounds": bounds}


def _structure_px(value) -> Optional[float]:
    """The optional ``residual_structure_px`` (spec >= 1.6): a positive number of px, or None."""
    if value is None:
        return None
    if not (is_number(value) and 0 < value <= MAX_IMAGE_SIDE_PX):
        raise JsonProblem(f"residual_structure_px must be a positive number of px, got {shown(value)}")
    return float(value)


def _checked(d: dict) -> dict:
    """The ModelSpec fields of a spec dict, every one checked (``JsonProblem`` names the field)."""
    camera = _checked_generic(d) if "generic" in d else _checked_camera(d)
    features = camera["features"]
    hidden = required(d, "hidden")
    if not isinstance(hidden, list) or not hidden:
        raise JsonProblem(f"hidden must be a list of layer widths, got {shown(hidden)}")
    provenance = d.get("provenance", {})
    if not isinstance(provenance, dict):
        raise JsonProblem(f"provenance must be an object, got {shown(provenance)}")
    digests = {}
    for key in (WEIGHTS_SHA256_KEY, CONTENT_SHA256_KEY):
        digests[key] = d.get(key)
        if digests[key] is not None and not (isinstance(digests[key], str) and _HEX64.fullmatch(digests[key])):
            raise JsonProblem(f"{key} must be 64 lowercase hex digits, got {shown(digests[key])}")
    return {
        **camera,
        "hidden": tuple(integer(h, "hidden", 1) for h in hidden),
        "provenance": dict(provenance),
        "uncertainty": Uncertainty.from_dict(d["uncertainty"], features.grid.n_cells) if "uncertainty" in d else None,
        "residual_structure_px": _structure_px(d.get("residual_structure_px")),
        "head": d.get("head", "mlp"),
        "weights_sha256": digests[WEIGHTS_SHA256_KEY],
        "content_sha256": digests[CONTENT_SHA256_KEY],
    }


@dataclass(frozen=True)
class GenericCamera:
    """What makes a model generic (spec >= 1.5): it infers K in a canonical camera of fx =
    focal_px (``rectify.user_camera.generic_pixel_map``) and has no camera of its own; delta_bounds
    (4, 2) [low, high] the plausible Delta K (fx, fy, cx, cy) in canonical px."""

    focal_px: float
    delta_bounds: np.ndarray

    def to_dict(self) -> dict:
        return {"focal_px": self.focal_px, "delta_bounds": np.asarray(self.delta_bounds).tolist()}


@dataclass(frozen=True)
class ModelSpec:
    """features: the grid feature; K_c (3, 3) px; image_size (width, height) px; K_bounds: per
    parameter (fx, fy, cx, cy) the [low, high] px range of plausible K (outside it, the runtime
    falls back to K_c); generic: None for a device model; for a generic one (spec >= 1.5) its
    canonical camera, and K_c, image_size and K_bounds are None until ``rectify.user_camera``
    resolves the spec for a camera (in canonical px); uncertainty: the model of the network's
    Delta K covariance (None in 1.0 specs); residual_structure_px: the largest residual structure
    (model px, ``geometry.residual_structure``) the model's training frames held, above which a
    frame keeps K_c (None before spec 1.6: ``checks.STRUCTURE_PX``); provenance: dataset sha256,
    seed, versions, command; weights_sha256 and content_sha256: the
    integrity hashes the model file's spec declared (None for a spec on its own, before 1.4 and 1.9).
    It belongs to one file, so ``to_dict`` leaves it out unless given one (export stamps it)."""

    features: FeatureSpec
    K_c: Optional[np.ndarray]
    image_size: Optional[tuple]
    K_bounds: Optional[np.ndarray]  # (4, 2) px
    hidden: tuple
    provenance: dict = field(default_factory=dict)
    generic: Optional[GenericCamera] = None
    uncertainty: Optional[Uncertainty] = None
    residual_structure_px: Optional[float] = None
    head: str = "mlp"
    weights_sha256: Optional[str] = field(default=None, compare=False)
    content_sha256: Optional[str] = field(default=None, compare=False)

    def __post_init__(self) -> None:
        problem = head_problem(self.head, self.features.data_step, "features.data_step")
        if problem:
            raise JsonProblem(problem)

    def to_dict(self, *, weights_sha256: Optional[str] = None, content_sha256: Optional[str] = None) -> dict:
        d = {"format": FORMAT, "version": VERSION, "features": self.features.to_dict()}
        if self.generic is not None:
            d["generic"] = self.generic.to_dict()
        else:
            d["K_c"] = k_params(self.K_c).tolist()
            d["image_size"] = [int(v) for v in self.image_size]
            d["K_bounds"] = np.asarray(self.K_bounds).tolist()
        d["hidden"], d["provenance"] = list(self.hidden), self.provenance
        if self.uncertainty is not None:
            d["uncertainty"] = self.uncertainty.to_dict()
        if self.residual_structure_px is not None:
            d["residual_structure_px"] = self.residual_structure_px
        if self.head != "mlp":
            d["head"] = self.head
        if weights_sha256 is not None:
            d[WEIGHTS_SHA256_KEY] = weights_sha256
        if content_sha256 is not None:
            d[CONTENT_SHA256_KEY] = content_sha256
        return d

    def to_json(self, *, weights_sha256: Optional[str] = None, content_sha256: Optional[str] = None) -> str:
        d = self.to_dict(weights_sha256=weights_sha256, content_sha256=content_sha256)
        return json.dumps(d, indent=1, sort_keys=True)

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

    def for_camera(self, camera: Optional[Camera], source: str = "model") -> ServedCamera:
        """This spec serving the user's ``camera`` (None: a device model's own camera).
        CameraError naming ``source`` for a generic model without a camera, or a camera a
        device model cannot serve (``rectify.user_camera.device_pixel_map``)."""
        if self.generic is None:
            if camera is None:
                return ServedCamera(self, None, self.K_c, tuple(self.image_size), self.K_bounds)
            pixels = device_pixel_map(k_params(self.K_c), self.image_size, camera, source)
            if pixels is None:
                return ServedCamera(self, None, camera.K, tuple(camera.image_size), self.K_bounds)
            K_c = pixels.K_to_user(self.K_c)  # the model's prior, in the camera's pixels
            return ServedCamera(self, pixels, K_c, tuple(camera.image_size), pixels.bounds_to_user(self.K_bounds))
        if camera is None:
            raise CameraError(
                f"{source} is a generic model: it needs your camera, K_c (3, 3) px and image_size (width, height) px "
                f"(Rectifier.load(..., K_c=..., image_size=...), or --camera FILE)"
            )
        grid = self.features.grid
        if not grid.fits(camera.image_size):
            raise CameraError(
                f"{source}: its {grid} grid has more cells than the {camera.image_size[0]}x{camera.image_size[1]} "
                f"image has pixels"
            )
        pixels = generic_pixel_map(camera, self.generic.focal_px)
        k = pixels.k_to_model(k_params(camera.K))
        size = tuple(float(v) * pixels.scale for v in camera.image_size)
        bounds = k[:, None] + self.generic.delta_bounds
        model = replace(self, K_c=k_matrix(k), image_size=size, K_bounds=bounds)
        return ServedCamera(model, pixels, camera.K, tuple(camera.image_size), pixels.bounds_to_user(bounds))

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


@dataclass(frozen=True)
class ServedCamera:
    """A spec serving one camera (``ModelSpec.for_camera``): ``model`` the spec in model px
    (K_c, image_size and K_bounds of the camera mapped onto the model's pixels); ``pixels`` the
    map from the camera's pixels onto the model's (None: the same); and in the camera's pixels
    K_c (3, 3) the prior used, image_size (width, height) and K_bounds (4, 2)."""

    model: ModelSpec
    pixels: Optional[PixelMap]
    K_c: np.ndarray
    image_size: tuple
    K_bounds: np.ndarray


def frame_within_bounds(k: list, K_bounds: list) -> bool:
    """The K-bounds rule on one frame's k = [fx, fy, cx, cy] (px, floats) against K_bounds as 4
    [low, high] lists: plain float comparisons, where a NaN fails too. The hot path's twin of
    ``ModelSpec.k_within_bounds``: 0.9 against 3.9 µs (models_spec/BENCHMARKS.md)."""
    return all(low <= v <= high for v, (low, high) in zip(k, K_bounds))
