"""Per-frame K rectification at run time: 2D-3D correspondences -> K, pose {W}->{C}.

numpy, OpenCV and ONNX Runtime only. ``Rectifier.rectify`` runs one frame through named
stages, each timed into ``timings_us`` under its name:

1. ``validate``: the input rules of ``rectify.checks`` (shapes, >= MIN_POINTS points, finite,
   inside the camera's image, not degenerate);
2. ``pnp_kc``: SQPnP pose {W}->{C0} under the prior K_c;
3. ``features``: the grid feature (``rectify.features.grid_features``) at that pose;
4. ``model``: one ONNX Runtime call, Delta K (px); the candidate K = K_c + Delta K, refused
   outside ``K_bounds``, and its covariance when the spec has an uncertainty model;
5. ``map`` (mode map only): the MAP fusion of that prior with the frame's points
   (``rectify.map_fit``, from the C0 pose turned to the network's principal point) replaces the
   candidate by its K, pose and posterior ``K_cov``; when it fails its checks, the DIME-Net
   candidate stands and ``fallback`` says why;
6. ``pnp_k``: SQPnP pose under the candidate K (unless map gave one);
7. ``refine`` (only with ``refine=True``): cv2.solvePnPRefineLM polish of the PnP poses;
8. ``check``: mean reprojection errors e(K) and e(K_c) over the given points, and the one
   fallback rule: a refused candidate gives way to K_c's own solution (``rectify.checks``).

``rectify_batch`` runs the same stages over B frames at once (the model once for all).

The camera: a device model serves its own camera, or a rescale or crop of it; a generic model
any camera, given to ``load``. A camera with lens distortion (``dist_coeffs``) has its points
undistorted to the pinhole camera of K_c after validation (``geometry.distortion``); K and the
poses are that pinhole camera's, and e and e_c are measured in the distorted image the points
came from. The stages run in the model's pixel frame (``rectify.camera``):
the points are mapped onto it after validation and K, Delta K, K_cov and the errors back
(nothing is mapped when the camera is the model's own).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property, partial
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from dimenet.runtime.assets import asset
from dimenet.runtime.errors import CameraError, InputError, ModelError
from dimenet.runtime.geometry import (
    MIN_POINTS,
    k_matrix,
    k_params,
    mean_reprojection_error,
    min_depths,
    solve_pnp_start,
)
from dimenet.runtime.geometry.distortion import mean_distorted_error, undistort_points
from dimenet.runtime.rectify.camera import Camera, PixelMap, checked_camera
from dimenet.runtime.rectify.checks import (
    BEHIND_REASON,
    NO_POSE_REASON,
    ImageBounds,
    behind_camera_error,
    bool_mask,
    check_spread,
    implausible_reason,
    loses_to_k_c,
    out_of_range,
    out_of_range_reason,
    real_array,
    spread_frames,
    too_few_distinct,
    worse_reason,
)
from dimenet.runtime.rectify.fast import all_inside, frame_error_and_depth, frame_mean_norm, frame_within_bounds
from dimenet.runtime.rectify.features import grid_features
from dimenet.runtime.rectify.inference import network_k, network_statistics
from dimenet.runtime.rectify.map_fit import map_rectify
from dimenet.runtime.rectify.model import OnnxModel, load_onnx_model, onnx_model_from_bytes
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.uncertainty import occupied_cells, thickness

DEFAULT_MODEL = "default_model.onnx"
DEFAULT_SOURCE = f"bundled default model ({DEFAULT_MODEL})"  # how errors and reports name it
MODES = ("dimenet", "map")


@dataclass(frozen=True)
class Rectification:
    """One frame. K (3, 3) px; rvec (3,) rad and tvec (3,) mm {W}->{C} under K; the mean Euclidean
    reprojection errors (px) over the given points under K and under K_c (each with its own
    pose); delta_k (4,) px the applied (dfx, dfy, dcx, dcy), 0 on fallback; fallback None or
    why K_c's solution (or in map mode, DIME-Net's) was returned; timings_us: microseconds per
    stage; K_cov (4, 4) px^2 the covariance of (fx, fy, cx, cy): the network's (mode dimenet)
    or the MAP posterior (mode map); None when K is K_c's or the model has no uncertainty;
    K_c (3, 3) px the prior used (``Rectifier.K_c``). ``covariance`` computes K_cov when first
    asked for: the hot path does not pay for it."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error_px: float
    reprojection_error_kc_px: float
    delta_k: np.ndarray
    fallback: Optional[str]
    timings_us: dict
    K_c: np.ndarray
    covariance: Optional[Callable[[], np.ndarray]] = field(default=None, repr=False, compare=False)

    @cached_property
    def K_cov(self) -> Optional[np.ndarray]:
        """(4, 4) px^2, computed on first access from ``covariance`` (None without one)."""
        return None if self.covariance is None else self.covariance()


@dataclass(frozen=True)
class BatchRectification:
    """B frames, as Rectification: K (B, 3, 3), rvec (B, 3), tvec (B, 3), errors (B,) px over
    each frame's valid points, delta_k (B, 4) px, fallback: one reason or None per frame;
    K_c (3, 3) px the prior used; K_cov (B, 4, 4) px^2, NaN for frames whose K is K_c's, or
    None without an uncertainty model."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error_px: np.ndarray
    reprojection_error_kc_px: np.ndarray
    delta_k: np.ndarray
    fallback: tuple
    K_c: np.ndarray
    K_cov: Optional[np.ndarray] = None


class _Lap:
    """Microseconds per stage: each call closes the stage that ran since the previous call."""

    __slots__ = ("timings", "_last")

    def __init__(self) -> None:
        self.timings: dict = {}
        self._last = time.perf_counter_ns()

    def __call__(self, stage: str) -> None:
        now = time.perf_counter_ns()
        self.timings[stage] = (now - self._last) / 1e3
        self._last = now


@dataclass
class _Candidate:
    """The K on offer for one frame while the stages run: K (3, 3) and delta_k (4,) px; its pose
    {W}->{C} (None until solved) and whether PnP solved it (refine may polish it); e (px), its
    mean error over the frame's points (None until measured); covariance: computes K_cov (None:
    none); note: why map's K gave way to DIME-Net's (None otherwise)."""

    K: np.ndarray
    delta_k: np.ndarray
    covariance: Optional[Callable[[], np.ndarray]]
    rvec: Optional[np.ndarray] = None
    tvec: Optional[np.ndarray] = None
    from_pnp: bool = False
    e: Optional[float] = None
    note: Optional[str] = None


@dataclass
class _BatchCandidates:
    """``_Candidate`` of B frames: K (B, 3, 3), delta_k (B, 4) px, their poses rvec, tvec (B, 3),
    K_cov (B, 4, 4) px^2 or None; reasons: why each frame's candidate was refused (None:
    standing); notes: map's soft fallbacks."""

    K: np.ndarray
    delta_k: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    K_cov: Optional[np.ndarray]
    reasons: list
    notes: list

    @property
    def standing(self) -> np.ndarray:
        return np.array([r is None for r in self.reasons])


@dataclass(frozen=True)
class _Frames:
    """A validated batch: points_2d (B, P, 2) px and points_3d (B, P, 3) mm float64; valid and
    infer (B, P) bool; mask: valid, or None when every point is valid; frames: each frame's valid
    points; invariants_3d: ``covariance_invariants_batch`` of the valid 3D points."""

    points_2d: np.ndarray
    points_3d: np.ndarray
    valid: np.ndarray
    infer: np.ndarray
    mask: Optional[np.ndarray]
    frames: list
    invariants_3d: tuple
    points_2d_image: np.ndarray  # the points as given (distorted): points_2d is their pinhole image


def _refine(points_2d, points_3d, K, rvec, tvec) -> tuple[np.ndarray, np.ndarray]:
    """cv2.solvePnPRefineLM polish of a pose: least-squares reprojection error under K."""
    r, t = cv2.solvePnPRefineLM(points_3d, points_2d, K, None, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy())
    return r.ravel(), t.ravel()


def _covariance_to_user(pixels: PixelMap, covariance: Callable[[], np.ndarray]) -> np.ndarray:
    return pixels.covariance_to_user(covariance())


def _in_frame(b: int, call, *args):
    """``call(*args)``, its InputError prefixed with the frame index ``b`` of a batch."""
    try:
        return call(*args)
    except InputError as exc:
        raise InputError(f"frame {b}: {exc}") from None


def load_model(path: Optional[str | Path] = None, *, threads: int = 1, providers=None) -> OnnxModel:
    """A ``dimenet-model/1`` .onnx file, or without a path the bundled default model (ModelError
    when this installation has none)."""
    if path is not None:
        return load_onnx_model(path, threads=threads, providers=providers)
    return onnx_model_from_bytes(default_model_bytes(), DEFAULT_SOURCE, threads=threads, providers=providers)


def default_model_bytes() -> bytes:
    """The bundled default model's file, or ModelError when this installation has none."""
    resource = asset(DEFAULT_MODEL)
    if not resource.is_file():
        raise ModelError(
            f"this installation has no bundled default model (dimenet/runtime/assets/{DEFAULT_MODEL}); "
            f"pass a model file from `dimenet export`"
        )
    return resource.read_bytes()


def _camera(model: OnnxModel, K_c, image_size) -> Optional[Camera]:
    """The camera of ``Rectifier.load``'s arguments: None (the model's own) without either; for a
    device model, ``image_size`` alone is a rescale of its camera and ``K_c`` alone keeps its
    image size."""
    if K_c is None and image_size is None:
        return None
    spec, source = model.spec, model.source
    if spec.generic is None and K_c is None:
        size = checked_camera(spec.K_c, image_size, "image_size").image_size
        K_c = PixelMap(scale=spec.image_size[0] / size[0]).K_to_user(spec.K_c)
    elif spec.generic is None and image_size is None:
        image_size = spec.image_size
    elif K_c is None or image_size is None:
        raise CameraError(
            f"{source} is a generic model: it needs both K_c (3, 3) px and image_size (width, height) px, "
            f"got only {'image_size' if K_c is None else 'K_c'}"
        )
    return checked_camera(K_c, image_size, "camera")


class Rectifier:
    """A loaded model ready to rectify frames of one camera. ``Rectifier.load(K_c=..., image_size=...)``
    uses the bundled (generic) default model. ``K_c`` (3, 3) px, ``image_size`` (width, height)
    px and ``K_bounds`` (4, 2) px: the camera served (the prior K_c used) and the plausible K, in
    the user's pixels."""

    def __init__(self, model: OnnxModel, mode: str = "dimenet", camera: Optional[Camera] = None) -> None:
        if mode not in MODES:
            raise InputError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        if mode == "map":
            model.spec.map_uncertainty(model.source)
        served = model.spec.for_camera(camera, model.source)
        spec, self._pixels = served.model, served.pixels
        self.model, self.mode, self._spec = model, mode, spec
        self.K_c, self.image_size, self.K_bounds = served.K_c.copy(), served.image_size, served.K_bounds
        self._uncertainty = spec.uncertainty
        self._n_channels = len(spec.features.channels)
        self._K_c = np.ascontiguousarray(spec.K_c, dtype=np.float64)
        self._k_c = k_params(spec.K_c)
        self._k_c_list = self._k_c.tolist()
        self._fx_c = float(self._k_c[0])
        self._K_bounds_list = spec.K_bounds.tolist()
        self._image = ImageBounds(self.image_size)
        self._user_px = 1.0 if self._pixels is None else 1.0 / self._pixels.scale  # user px per model px
        self.dist_coeffs = None if camera is None else camera.dist_coeffs
        self._lens_K = None if camera is None else camera.lens_K
        self.K_c.setflags(write=False)

    @classmethod
    def load(
        cls,
        path: Optional[str | Path] = None,
        *,
        K_c=None,
        image_size=None,
        dist_coeffs=None,
        threads: int = 1,
        providers: Optional[Sequence[str]] = None,
        mode: str = "dimenet",
    ) -> Rectifier:
        """From a ``dimenet-model/1`` .onnx file; without a path, the bundled default model.
        ``K_c`` (3, 3) px and ``image_size`` (width, height) px: the camera (OpenCV's pixel
        convention, the centre of the top-left pixel at (0, 0)); a generic model needs both, a
        device model keeps its own camera without them and accepts a rescale or crop of it
        (``image_size`` alone: a rescale). ``dist_coeffs``: the lens's distortion about K_c,
        OpenCV's 4/5/8/12/14 coefficients (the points are then as the distorted image holds
        them; needs K_c). ``mode``: "dimenet" (the paper's method) or "map" (the
        network's K as a prior, fused with the frame's own points). CameraError for a camera the
        model cannot serve."""
        model = load_model(path, threads=threads, providers=providers)
        camera = _camera(model, K_c, image_size)
        if dist_coeffs is not None:
            if camera is None:
                raise CameraError("dist_coeffs: the distortion is stated about K_c: give K_c (and image_size) with it")
            camera = checked_camera(camera.K, camera.image_size, "camera", dist_coeffs)
        return cls(model, mode, camera)

    @property
    def spec(self) -> ModelSpec:
        """The model's own spec (a generic model's has no camera: see ``K_c``, ``image_size``)."""
        return self.model.spec

    def k_within_bounds(self, k: np.ndarray) -> bool:
        """The K-bounds rule (``ModelSpec.k_within_bounds``) for k (4,) px in the camera's pixels."""
        return frame_within_bounds(list(k), self.K_bounds.tolist())

    # -- one frame ---------------------------------------------------------------------------

    def _validated(self, points_2d, points_3d) -> tuple[np.ndarray, np.ndarray, tuple]:
        """Stage validate: one frame's points as float64 (N, 2) px and (N, 3) mm with the
        ``covariance_invariants`` of the 3D points, or InputError naming the problem."""
        p2 = real_array(points_2d, "points_2d", "(N, 2)", 2, 2)
        p3 = real_array(points_3d, "points_3d", "(N, 3)", 2, 3)
        n = len(p2)
        if len(p3) != n:
            raise InputError(f"points_2d has {n} points and points_3d {len(p3)}: they must correspond one to one")
        if n < MIN_POINTS:
            raise InputError(f"{n} points: rectification needs at least {MIN_POINTS}")
        if not all_inside(self._image, p2, p3):
            self._image.raise_bad_values(p2, p3, True, "")
        invariants_3d = check_spread(p2, p3)
        distinct = too_few_distinct(p2, p3, MIN_POINTS)
        if distinct is not None:
            raise InputError(f"{distinct} distinct points of {n}: rectification needs at least {MIN_POINTS}")
        return p2, p3, invariants_3d

    def _frame_covariance(self, feats: np.ndarray, n_points: int, pmd_px: float, invariants_3d: tuple) -> np.ndarray:
        """The network's 4x4 covariance (px^2) of one frame from its (1, D) feature, point count,
        mean PMD (px) and the ``covariance_invariants`` of its 3D points."""
        return self._uncertainty.frame_covariance(
            n_points, occupied_cells(feats, self._n_channels)[0], pmd_px, thickness(*invariants_3d)
        )

    def _user_k(self, k) -> np.ndarray:
        """(4,) (fx, fy, cx, cy) model px -> the user's px (for the reasons)."""
        return np.asarray(k) if self._pixels is None else self._pixels.k_to_user(k)

    def _network_candidate(self, delta_k, feats, n_points: int, pmd_px: float, invariants_3d: tuple):
        """Stage model's end: (candidate, None), or (None, why) when K = K_c + Delta K breaks the
        K-bounds rule."""
        k = [c + d for c, d in zip(self._k_c_list, delta_k.tolist())]
        if not frame_within_bounds(k, self._K_bounds_list):
            return None, implausible_reason(delta_k, self._user_k(k))
        covariance = None
        if self._uncertainty is not None:
            covariance = partial(self._frame_covariance, feats, n_points, pmd_px, invariants_3d)
        return _Candidate(K=k_matrix(k), delta_k=delta_k, covariance=covariance), None

    def _map(self, p2, p3, k_net: np.ndarray, K_cov_net: np.ndarray, rvec_c0, tvec_c0):
        """Stage map of one frame, shared by ``rectify`` and ``rectify_batch``: (the MAP fit,
        None), or (None, the note saying why DIME-Net's K stands)."""
        fit, why = map_rectify(
            p2,
            p3,
            k_net,
            K_cov_net,
            self._spec.K_bounds,
            self._K_c,
            pose=(rvec_c0, tvec_c0),
            uncertainty=self._uncertainty,
        )
        return (fit, None) if why is None else (None, f"map: {why}; DIME-Net's K is returned")

    def rectify(self, points_2d, points_3d, *, refine: bool = False) -> Rectification:
        """K and pose of one frame from its correspondences: points_2d (N, 2) px, points_3d (N, 3) mm in {W}.

        Lists and other real dtypes are accepted and cast to float64. Raises InputError for
        unusable input. See the module docstring for the stages and ``rectify.checks`` for the
        rules.
        """
        lap = _Lap()
        p2, p3, invariants_3d = self._validated(points_2d, points_3d)
        p2_image = p2
        if self.dist_coeffs is not None:
            p2 = undistort_points(p2, self._lens_K, self.dist_coeffs)
        if self._pixels is not None:
            p2 = self._pixels.points_to_model(p2)
        lap("validate")
        spec, K_c = self._spec, self._K_c
        rvec_c0, tvec_c0 = solve_pnp_start(p2, p3, K_c)
        lap("pnp_kc")
        feats, points = grid_features(
            p2[None],
            p3[None],
            None,
            K_c,
            spec.image_size,
            spec.features,
            poses=(rvec_c0[None], tvec_c0[None]),
            return_points=True,
        )
        if not cv2.checkRange(points[0, 4], True, 0.0, np.inf)[0]:  # 1 / Z_C0 <= 0: a point behind the camera
            raise behind_camera_error(int(np.count_nonzero(points[0, 4] <= 0)), len(p2))
        lap("features")
        delta_k = self.model.frame_delta_k(feats)
        lap("model")
        e_c = frame_mean_norm(points[0, :2])  # the feature's PMD: the residuals under K_c at the C0 pose
        if out_of_range(e_c, self._fx_c):
            cand, reason = None, out_of_range_reason(e_c, self._fx_c, self._user_px)
        else:
            cand, reason = self._network_candidate(delta_k, feats, len(p2), e_c, invariants_3d)
        if reason is None and self.mode == "map":
            # From the C0 pose: MAP needs no PnP under the network's K, unless it fails.
            fit, cand.note = self._map(p2, p3, self._k_c + delta_k, cand.covariance(), rvec_c0, tvec_c0)
            if fit is not None:
                cand = _Candidate(
                    K=k_matrix(fit.k),
                    delta_k=fit.k - self._k_c,
                    covariance=partial(np.array, fit.K_cov),
                    rvec=fit.rvec,
                    tvec=fit.tvec,
                    e=frame_mean_norm(fit.residuals.T),
                )
            lap("map")
        if reason is None and cand.rvec is None:
            try:
                cand.rvec, cand.tvec = solve_pnp_start(p2, p3, cand.K)
                cand.from_pnp = True
            except InputError:
                reason = NO_POSE_REASON
            lap("pnp_k")
        if refine:
            rvec_c0, tvec_c0 = _refine(p2, p3, K_c, rvec_c0, tvec_c0)
            if reason is None and cand.from_pnp:
                cand.rvec, cand.tvec = _refine(p2, p3, cand.K, cand.rvec, cand.tvec)
            e_c = frame_error_and_depth(p2, p3, K_c, rvec_c0, tvec_c0)[0]
            lap("refine")
        if reason is None and cand.e is None:
            cand.e, depth = frame_error_and_depth(p2, p3, cand.K, cand.rvec, cand.tvec)
            if depth <= 0:
                reason = BEHIND_REASON
        if reason is None and loses_to_k_c(cand.e, e_c, self._fx_c):
            reason = worse_reason(cand.e, e_c, self._fx_c, self._user_px)
        if reason is not None:  # the one fallback rule: K_c's own solution
            cand = _Candidate(
                K=self.K_c.copy(), delta_k=np.zeros(4), covariance=None, rvec=rvec_c0, tvec=tvec_c0, e=e_c, note=reason
            )
        lap("check")
        if self._pixels is not None:
            result = self._user_result(cand, e_c, lap.timings, reason is not None)
        else:
            result = Rectification(
                K=cand.K,
                rvec=cand.rvec,
                tvec=cand.tvec,
                reprojection_error_px=cand.e,
                reprojection_error_kc_px=e_c,
                delta_k=cand.delta_k,
                fallback=cand.note,
                timings_us=lap.timings,
                K_c=self.K_c,
                covariance=cand.covariance,
            )
        if self.dist_coeffs is None:
            return result
        e, e_c = self._image_errors(
            p2_image[None],
            p3[None],
            None,
            np.stack([result.K, self.K_c]),
            (result.rvec, rvec_c0),
            (result.tvec, tvec_c0),
        )
        return replace(result, reprojection_error_px=float(e[0]), reprojection_error_kc_px=float(e_c[0]))

    def _image_errors(self, p2_image, p3, valid, K, rvecs, tvecs) -> np.ndarray:
        """Mean errors (px) in the distorted image of (B, N) points for each of the candidate
        (K, pose) pairs: K (M, 3, 3) px, rvecs and tvecs M arrays (B, 3) or (3,) -> (M, B)."""
        return np.stack(
            [
                mean_distorted_error(
                    p2_image,
                    p3,
                    valid,
                    K[m],
                    np.reshape(rvecs[m], (-1, 3)),
                    np.reshape(tvecs[m], (-1, 3)),
                    self._lens_K,
                    self.dist_coeffs,
                )
                for m in range(len(K))
            ]
        )

    def _user_result(self, cand: _Candidate, e_c: float, timings: dict, fell_back: bool) -> Rectification:
        """The result of one frame whose stages ran in the model's pixels, in the camera's
        (``rectify.camera.PixelMap``; the pose is the same in both); on fallback K is K_c."""
        pixels, to_user = self._pixels, self._user_px
        covariance = cand.covariance
        if covariance is not None:
            covariance = partial(_covariance_to_user, pixels, covariance)
        return Rectification(
            K=self.K_c.copy() if fell_back else pixels.K_to_user(cand.K),
            rvec=cand.rvec,
            tvec=cand.tvec,
            reprojection_error_px=cand.e * to_user,
            reprojection_error_kc_px=e_c * to_user,
            delta_k=cand.delta_k * to_user,
            fallback=cand.note,
            timings_us=timings,
            K_c=self.K_c,
            covariance=covariance,
        )

    # -- B frames ----------------------------------------------------------------------------

    def _validated_batch(self, points_2d, points_3d, valid, infer_mask) -> _Frames:
        """Stage validate of B frames, or InputError naming the first unusable frame."""
        p2 = real_array(points_2d, "points_2d", "(B, P, 2)", 3, 2)
        p3 = real_array(points_3d, "points_3d", "(B, P, 3)", 3, 3)
        if p3.shape[:2] != p2.shape[:2]:
            raise InputError(f"points_2d has shape {p2.shape} and points_3d {p3.shape}: (B, P) must agree")
        if len(p2) == 0:
            raise InputError("points_2d: an empty batch (B = 0), nothing to rectify")
        valid = bool_mask(valid, "valid", p2.shape[:2])
        infer = valid if infer_mask is None else bool_mask(infer_mask, "infer_mask", p2.shape[:2])
        if np.any(infer & ~valid):
            raise InputError("infer_mask: must be a subset of valid")
        counts = valid.sum(1)
        if np.any(counts < MIN_POINTS):
            b = int(np.argmin(counts))
            raise InputError(f"frame {b}: {int(counts[b])} valid points, rectification needs at least {MIN_POINTS}")
        every = bool(valid.all())
        mask = None if every else valid
        inside = (
            all_inside(self._image, p2, p3)
            if every
            else all_inside(self._image, np.where(valid[..., None], p2, 0.0), np.where(valid[..., None], p3, 0.0))
        )
        if not inside:
            for b in np.flatnonzero(np.any(valid & ~self._image.inside(p2, p3), 1)):
                self._image.raise_bad_values(p2[b], p3[b], valid[b], f"frame {b}: ")
        p2_image = p2
        if self.dist_coeffs is not None:
            p2 = undistort_points(p2, self._lens_K, self.dist_coeffs)
        if self._pixels is not None:
            p2 = self._pixels.points_to_model(p2)
        frames = [(p2[b], p3[b]) if every else (p2[b][valid[b]], p3[b][valid[b]]) for b in range(len(p2))]
        spread_3d, invariants_3d = spread_frames(p3, mask)
        spread = spread_3d & spread_frames(p2, mask)[0]
        for b in np.flatnonzero(~spread):
            _in_frame(b, check_spread, *frames[b])
        for b, (x, X) in enumerate(frames):
            distinct = too_few_distinct(x, X, MIN_POINTS)
            if distinct is not None:
                raise InputError(
                    f"frame {b}: {distinct} distinct valid points of {len(x)}: "
                    f"rectification needs at least {MIN_POINTS}"
                )
        return _Frames(p2, p3, valid, infer, mask, frames, invariants_3d, p2_image)

    def _c0_poses(self, fr: _Frames) -> tuple[np.ndarray, np.ndarray]:
        """Stage pnp_kc of B frames: SQPnP poses {W}->{C0} under K_c on each frame's valid points."""
        B = len(fr.frames)
        rvec_c0, tvec_c0 = np.empty((B, 3)), np.empty((B, 3))
        for b, (x, X) in enumerate(fr.frames):
            rvec_c0[b], tvec_c0[b] = _in_frame(b, solve_pnp_start, x, X, self._K_c)
        behind = min_depths(fr.points_3d, fr.mask, rvec_c0, tvec_c0) <= 0
        if behind.any():
            b = int(np.argmax(behind))
            x, X = fr.frames[b]
            Z = X @ cv2.Rodrigues(rvec_c0[b])[0][2] + tvec_c0[b, 2]
            raise InputError(f"frame {b}: {behind_camera_error(int(np.count_nonzero(Z <= 0)), len(X))}")
        return rvec_c0, tvec_c0

    def _inference_poses(self, fr: _Frames, rvec_c0, tvec_c0, reasons: list):
        """The C0 poses of the inference points: the valid points' when they are the inference
        points, else SQPnP under K_c on each frame's inference points; frames with too few of
        them or no pose get a fallback reason and an empty inference mask. -> (infer, rvec, tvec)."""
        if fr.infer is fr.valid:
            return fr.infer, rvec_c0, tvec_c0
        rvec, tvec, infer = rvec_c0.copy(), tvec_c0.copy(), fr.infer.copy()
        for b in range(len(infer)):
            n = int(infer[b].sum())
            try:
                if n < MIN_POINTS:
                    raise InputError(f"{n} inference points, fewer than {MIN_POINTS}")
                rvec[b], tvec[b] = solve_pnp_start(fr.points_2d[b][infer[b]], fr.points_3d[b][infer[b]], self._K_c)
            except InputError as exc:
                reasons[b], infer[b] = f"no K inferred: {exc}", False
        return infer, rvec, tvec

    def _candidates(self, fr: _Frames, net, rvec_c0, tvec_c0, e_c0, reasons: list) -> _BatchCandidates:
        """Stages model's end and pnp_k of B frames: the range rule on e_c0 (B,) px, each frame's
        mean error under K_c at its C0 pose, and the K-bounds rule, then SQPnP under each standing
        K on the frame's valid points."""
        cand = _BatchCandidates(
            K=k_matrix(net.k),
            delta_k=net.delta_k,
            rvec=rvec_c0.copy(),
            tvec=tvec_c0.copy(),
            K_cov=None,
            reasons=reasons,
            notes=[None] * len(reasons),
        )
        far = out_of_range(e_c0, self._fx_c)
        for b, (x, X) in enumerate(fr.frames):
            if reasons[b] is None and far[b]:
                reasons[b] = out_of_range_reason(e_c0[b], self._fx_c, self._user_px)
            if reasons[b] is None and not net.plausible[b]:
                reasons[b] = implausible_reason(net.delta_k[b], self._user_k(net.k[b]))
            if reasons[b] is None:
                try:
                    cand.rvec[b], cand.tvec[b] = solve_pnp_start(x, X, cand.K[b])
                except InputError:
                    reasons[b] = NO_POSE_REASON
        return cand

    def _covariances(self, cand: _BatchCandidates, net, fr: _Frames, infer, pending, pmd_px) -> None:
        """The network's K_cov of the pending frames (NaN elsewhere), in place. With K inferred
        from the valid points, validation's 3D invariants and ``pmd_px`` are those of the
        inference points."""
        cand.K_cov = np.full((len(infer), 4, 4), np.nan)
        if not pending.any():
            return
        if pmd_px is not None:
            known = (pmd_px[pending], tuple(a[pending] for a in fr.invariants_3d))
            stats = network_statistics(net, pending, infer, fr.points_3d, self._n_channels, *known)
        else:
            stats = network_statistics(net, pending, infer, fr.points_3d, self._n_channels)
        cand.K_cov[pending] = self._uncertainty.covariance(stats)

    def _maps(self, cand: _BatchCandidates, net, fr: _Frames, infer, poses_i, pending) -> None:
        """Stage map of the pending frames, in place: each frame's MAP K from its inference points
        and their C0 pose, its pose on its valid points; a failed fit leaves DIME-Net's K and a note."""
        for b in np.flatnonzero(pending):
            m = infer[b]
            x, X = fr.points_2d[b][m], fr.points_3d[b][m]
            fit, cand.notes[b] = self._map(x, X, net.k[b], cand.K_cov[b], poses_i[0][b], poses_i[1][b])
            if fit is not None:
                cand.K[b], cand.delta_k[b], cand.K_cov[b] = k_matrix(fit.k), fit.k - self._k_c, fit.K_cov
                cand.rvec[b], cand.tvec[b] = (
                    (fit.rvec, fit.tvec) if infer is fr.valid else solve_pnp_start(*fr.frames[b], cand.K[b])
                )

    def _errors(self, cand: _BatchCandidates, fr: _Frames, pending, e_c) -> np.ndarray:
        """Stage check of B frames: e(K) over each frame's valid points (e_c where not pending),
        and the cheirality and worse-than-K_c rules into ``cand.reasons``."""
        e = e_c.copy()
        if pending.any():
            mask = None if fr.mask is None else fr.mask[pending]
            behind = min_depths(fr.points_3d[pending], mask, cand.rvec[pending], cand.tvec[pending]) <= 0
            for b in np.flatnonzero(pending)[behind]:
                cand.reasons[b] = BEHIND_REASON
            pending = pending & cand.standing
        if pending.any():
            e[pending] = mean_reprojection_error(
                fr.points_2d[pending],
                fr.points_3d[pending],
                None if fr.mask is None else fr.mask[pending],
                cand.K[pending],
                cand.rvec[pending],
                cand.tvec[pending],
            )
        for b in np.flatnonzero(pending & loses_to_k_c(e, e_c, self._fx_c)):
            cand.reasons[b] = worse_reason(e[b], e_c[b], self._fx_c, self._user_px)
        return e

    def rectify_batch(
        self, points_2d, points_3d, valid, *, infer_mask=None, refine: bool = False
    ) -> BatchRectification:
        """K and pose of B frames: points_2d (B, P, 2) px, points_3d (B, P, 3) mm, valid (B, P) bool.

        The stages of ``rectify`` over all frames at once: features of all frames are computed
        together and the model runs once. Poses and errors use each frame's valid points; K is
        inferred from ``infer_mask`` (B, P), a subset of valid (default: valid). A frame with
        fewer than MIN_POINTS inference points, or no pose from them, falls back to K_c. Same
        results as ``rectify`` frame by frame when infer_mask is valid. Raises InputError naming
        the first unusable frame.
        """
        fr = self._validated_batch(points_2d, points_3d, valid, infer_mask)
        rvec_c0, tvec_c0 = self._c0_poses(fr)
        reasons: list = [None] * len(fr.frames)
        infer, *poses_i = self._inference_poses(fr, rvec_c0, tvec_c0, reasons)
        net = network_k(self._spec, self.model.delta_k, fr.points_2d, fr.points_3d, infer, tuple(poses_i))
        # With K inferred from the valid points, the feature's PMD rows are their residuals under K_c
        # at the C0 pose: their mean norm is e_c, and the uncertainty's PMD statistic.
        pmd_px = net.pmd_norms(fr.mask) if infer is fr.valid else None
        if pmd_px is not None:
            e_c0 = pmd_px
        else:
            e_c0 = mean_reprojection_error(fr.points_2d, fr.points_3d, fr.mask, self._K_c, rvec_c0, tvec_c0)
        cand = self._candidates(fr, net, rvec_c0, tvec_c0, e_c0, reasons)
        pending = cand.standing
        if self._uncertainty is not None:
            self._covariances(cand, net, fr, infer, pending, pmd_px)
        if self.mode == "map":
            self._maps(cand, net, fr, infer, poses_i, pending)
        if refine:
            for b, (x, X) in enumerate(fr.frames):
                rvec_c0[b], tvec_c0[b] = _refine(x, X, self._K_c, rvec_c0[b], tvec_c0[b])
                if pending[b]:
                    cand.rvec[b], cand.tvec[b] = _refine(x, X, cand.K[b], cand.rvec[b], cand.tvec[b])
        if refine:
            e_c = mean_reprojection_error(fr.points_2d, fr.points_3d, fr.mask, self._K_c, rvec_c0, tvec_c0)
        else:
            e_c = e_c0  # the C0 pose and K_c on all valid points
        e = self._errors(cand, fr, pending, e_c)
        fell_back = ~cand.standing  # the one fallback rule: K_c's own solution
        cand.rvec[fell_back], cand.tvec[fell_back], e[fell_back] = (
            rvec_c0[fell_back],
            tvec_c0[fell_back],
            e_c[fell_back],
        )
        K, delta_k, K_cov = cand.K, cand.delta_k, cand.K_cov
        if self._pixels is not None:
            pixels = self._pixels
            K, delta_k, e, e_c = pixels.K_to_user(K), delta_k * self._user_px, e * self._user_px, e_c * self._user_px
            K_cov = None if K_cov is None else pixels.covariance_to_user(K_cov)
        K[fell_back], delta_k[fell_back] = self.K_c, 0.0
        if K_cov is not None:
            K_cov[fell_back] = np.nan
        if self.dist_coeffs is not None:
            p3 = np.where(fr.valid[..., None], fr.points_3d, 0.0)
            K_cs = np.broadcast_to(self.K_c, K.shape)
            e, e_c = self._image_errors(
                fr.points_2d_image, p3, fr.mask, np.stack([K, K_cs]), (cand.rvec, rvec_c0), (cand.tvec, tvec_c0)
            )
        return BatchRectification(
            K=K,
            rvec=cand.rvec,
            tvec=cand.tvec,
            reprojection_error_px=e,
            reprojection_error_kc_px=e_c,
            delta_k=delta_k,
            fallback=tuple(r if r is not None else n for r, n in zip(reasons, cand.notes)),
            K_c=self.K_c,
            K_cov=K_cov,
        )
