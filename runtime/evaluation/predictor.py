"""From a trained model to per-frame K: the part shared by every model backend.

A backend (the ONNX session in the runtime, or a torch RUN_DIR from dimenet.training,
registered under the ``dimenet.predictors`` entry-point group) only maps features to
Delta K; building the features and turning Delta K into K is ``rectify.inference``'s, shared
with the rectifier's batches.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from dimenet.runtime.errors import InputError, ModelError
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import MIN_POINTS, k_matrix
from dimenet.runtime.plugins import entry_points
from dimenet.runtime.rectify.features import grid_features
from dimenet.runtime.rectify.inference import NetworkK, network_k, network_statistics
from dimenet.runtime.rectify.model import OnnxModel, load_model, load_onnx_model, resolve_model
from dimenet.runtime.rectify.spec import ModelSpec, ServedCamera
from dimenet.runtime.rectify.uncertainty import STATISTICS
from dimenet.runtime.rectify.user_camera import Camera


@dataclass(frozen=True)
class KPrediction:
    """Per frame of F: K (F, 3, 3) px (K_c where not predicted); predicted (F,) bool, False
    when the frame has too few inference points, no feature (``readable_network_k``) or the prediction
    is implausible; stats
    (F, 4) the uncertainty statistics of the inference points (NaN where not predicted);
    K_cov (F, 4, 4) px^2 the network's covariance of (fx, fy, cx, cy), None when the spec has
    no uncertainty model (NaN where not predicted)."""

    K: np.ndarray
    predicted: np.ndarray
    stats: np.ndarray
    K_cov: Optional[np.ndarray]


@dataclass(frozen=True)
class Predictor:
    """A ``DeltaKModel`` (``rectify.model``). spec: the model's dimenet-model/1 spec; delta_k: features (B, D)
    float32 -> (B, 4) px; camera: the camera served (None: a device model's own; a generic model needs one, see
    ``for_camera``). ``K_c``, ``K_bounds`` and ``image_size`` are the camera's, in its pixels."""

    spec: ModelSpec
    delta_k: Callable[[np.ndarray], np.ndarray]
    source: str
    camera: Optional[Camera] = None

    @classmethod
    def of_model(cls, model: OnnxModel) -> Predictor:
        """A loaded ONNX model (``rectify.model``) as a predictor (no camera yet)."""
        return cls(spec=model.spec, delta_k=model.delta_k, source=model.source)

    def for_camera(self, camera: Optional[Camera]) -> Predictor:
        """This predictor serving ``camera`` (CameraError when the model cannot)."""
        predictor = replace(self, camera=camera)
        predictor.served  # noqa: B018 (resolved now: a camera the model cannot serve fails here)
        return predictor

    @cached_property
    def served(self) -> ServedCamera:
        """The spec serving the camera (``ModelSpec.for_camera``; a generic model's CameraError
        without one)."""
        return self.spec.for_camera(self.camera, self.source)

    @property
    def image_size(self) -> tuple:
        return self.served.image_size

    @property
    def K_c(self) -> np.ndarray:
        """(3, 3) px the prior, in the camera's pixels."""
        return self.served.K_c

    @property
    def K_bounds(self) -> np.ndarray:
        """(4, 2) px the plausible K range, in the camera's pixels."""
        return self.served.K_bounds

    def predict(self, frames: Dataset) -> KPrediction:
        """K and, with an uncertainty model, its covariance per frame from its inference points."""
        spec, pixels = self.served.model, self.served.pixels
        size = self.image_size
        if tuple(frames.image_size.tolist()) != size:
            raise ModelError(
                f"{self.source}: serves {size[0]}x{size[1]} px images, the dataset has "
                f"{frames.image_size[0]}x{frames.image_size[1]} (give its camera: --camera FILE)"
            )
        F = frames.n_frames
        K = np.broadcast_to(self.K_c, (F, 3, 3)).copy()
        stats = np.full((F, len(STATISTICS)), np.nan)
        predicted = np.zeros(F, bool)
        usable = frames.infer_mask.sum(1) >= MIN_POINTS
        if usable.any():
            sub = frames.select(usable)
            points_2d = sub.points_2d if pixels is None else pixels.points_to_model(sub.points_2d)
            net, read = readable_network_k(spec, self.delta_k, points_2d, sub.points_3d, sub.infer_mask)
            ok = net.plausible & read
            rows = np.flatnonzero(usable)[ok]
            k = net.k[ok] if pixels is None else pixels.k_to_user(net.k[ok])
            K[rows], predicted[rows] = k_matrix(k), True
            stats[rows] = network_statistics(net, ok, sub.infer_mask, sub.points_3d, spec.features)
        K_cov = None
        if spec.uncertainty is not None:
            K_cov = np.full((F, 4, 4), np.nan)
            K_cov[predicted] = spec.uncertainty.covariance(stats[predicted])
            if pixels is not None:
                K_cov = pixels.covariance_to_user(K_cov)
        return KPrediction(K=K, predicted=predicted, stats=stats, K_cov=K_cov)

    def frame_delta_k(self, features: np.ndarray) -> np.ndarray:
        """One frame's (1, D) feature -> Delta K (4,) px: the model interface ``Rectifier`` calls."""
        return np.asarray(self.delta_k(np.asarray(features, np.float32)), dtype=np.float64)[0]

    def predict_k(self, frames: Dataset) -> np.ndarray:
        """K (F, 3, 3) px per frame from its inference points; K_c where the frame has too few
        inference points or the prediction is outside the plausible bounds."""
        return self.predict(frames).K


def load_predictor(path: str | Path) -> Predictor:
    """A predictor from a model (``resolve_model``): a bundled model's name, a RUN_DIR (needs the train extra)
    or an exported .onnx."""
    ref = resolve_model(path)
    if ref.bundled is not None:
        return Predictor.of_model(load_model(ref.bundled))
    kind = "run_dir" if ref.run_dir else ref.path.suffix.lstrip(".").lower()
    loaders = entry_points("dimenet.predictors")
    if kind not in loaders:
        raise ModelError(
            f"{ref.path}: not a model this installation can load (known kinds: {', '.join(sorted(loaders))})"
        )
    return loaders[kind].load()(ref.path)


def load_onnx_predictor(path: str | Path) -> Predictor:
    """Entry point ``onnx`` of ``dimenet.predictors``: a .onnx file as a Predictor."""
    return Predictor.of_model(load_onnx_model(path))


def readable_network_k(spec: ModelSpec, delta_k, points_2d, points_3d, mask) -> tuple[NetworkK, np.ndarray]:
    """``network_k`` of F frames (model px), and which it read (F,) bool: a frame whose feature cannot be formed
    (an InputError of ``grid_features``: no C0 pose, or a data step with no solution)
    is left unread, its inference points dropped, where one such frame would fail the F (a training's uncertainty
    fit draws single planes and sparse points, whose data step can be singular)."""
    try:
        return network_k(spec, delta_k, points_2d, points_3d, mask), np.ones(len(mask), bool)
    except InputError:
        pass
    read = np.ones(len(mask), bool)
    for f in range(len(mask)):
        try:
            grid_features(
                points_2d[f : f + 1], points_3d[f : f + 1], mask[f : f + 1], spec.K_c, spec.image_size, spec.features
            )
        except InputError:
            read[f] = False
    return network_k(spec, delta_k, points_2d, points_3d, mask & read[:, None]), read
