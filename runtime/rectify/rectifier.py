"""Per-frame K rectification at run time: 2D-3D correspondences -> K, pose {W}->{C}.

numpy, OpenCV and ONNX Runtime, and the optional compiled core (``runtime.native``: parts of validate,
the feature, the pose under K and e(K); models_spec/BENCHMARKS.md). ``Rectifier.rectify`` runs one
frame through named stages (``rectify.stages``, each beside its batch twin; validation in
``rectify.checks``, the check in ``rectify.check_stage``), each timed into ``timings_us`` under its name:

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
6. ``pnp_k``: the pose under the candidate K (unless map gave one): two Gauss-Newton steps from the
   C0 pose (``geometry.pose_step``), with e(K) there;
7. ``refine`` (only with ``refine=True``): cv2.solvePnPRefineLM polish of the PnP poses;
8. ``check``: mean reprojection errors e(K) and e(K_c) over the given points, the worse rule and,
   where K removes less than half of e(K_c), the structure rule on the residuals under K_c at the
   C0 pose (``geometry.residual_structure``, ``checks.structured``: structure that neither OIS nor
   corner noise makes, which the network read as OIS) and the evidence rule; where they refuse K at
   the steps' pose, again at SQPnP's pose under K; a refused candidate gives way to K_c's own
   solution (``rectify.checks``).

``rectify_batch`` runs the same stages over B frames at once (the model once for all).

The camera: a device model serves its own camera, or a rescale or crop of it; a generic model
any camera, given to ``load``. A camera with lens distortion (``dist_coeffs``) has its points
undistorted to the pinhole camera of K_c after validation (``geometry.distortion``); K and the
poses are that pinhole camera's, and e and e_c are measured in the distorted image the points
came from. The stages run in the model's pixel frame (``rectify.user_camera``):
the points are mapped onto it after validation and K, Delta K, K_cov and the errors back
(nothing is mapped when the camera is the model's own).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Optional

import numpy as np
from numpy.typing import ArrayLike

from dimenet.runtime import native
from dimenet.runtime.errors import CameraError, InputError
from dimenet.runtime.geometry import k_matrix, k_params, mean_reprojection_error
from dimenet.runtime.native import solve_pnp_start as pnp
from dimenet.runtime.rectify import check_stage, stages
from dimenet.runtime.rectify.checks import real_array, validated_batch, validated_frame
from dimenet.runtime.rectify.inference import network_k
from dimenet.runtime.rectify.model import OnnxModel, load_model
from dimenet.runtime.rectify.results import BatchRectification, NetworkEstimate, Rectification
from dimenet.runtime.rectify.spec import ModelSpec, frame_within_bounds
from dimenet.runtime.rectify.user_camera import Camera, PixelMap, checked_camera, checked_image_size

MODES = ("dimenet", "map")


class Lap:
    """Microseconds per stage: each call closes the stage that ran since the previous call."""

    __slots__ = ("timings", "_last")

    def __init__(self) -> None:
        self.timings: dict = {}
        self._last = time.perf_counter_ns()

    def __call__(self, stage: str) -> None:
        now = time.perf_counter_ns()
        self.timings[stage] = (now - self._last) / 1e3
        self._last = now


def _camera(model: OnnxModel, K_c, image_size) -> Optional[Camera]:
    """The camera of ``Rectifier.load``'s arguments: None (the model's own) without either; for a
    device model, ``image_size`` alone is a rescale of its camera and ``K_c`` alone keeps its
    image size."""
    if K_c is None and image_size is None:
        return None
    spec, source = model.spec, model.source
    if spec.generic is None and K_c is None:
        size = checked_image_size(image_size, "image_size")
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
        self.model, self.mode = model, mode
        self._cam = stages.ModelCamera.build(served, camera)
        self.K_c, self.image_size, self.K_bounds = self._cam.K_c_user, served.image_size, served.K_bounds
        self.dist_coeffs = self._cam.dist_coeffs

    @classmethod
    def load(
        cls,
        path: Optional[str | Path] = None,
        *,
        K_c: Optional[ArrayLike] = None,
        image_size: Optional[Sequence[int]] = None,
        dist_coeffs: Optional[ArrayLike] = None,
        threads: int = 1,
        providers: Optional[Sequence[str]] = None,
        mode: str = "dimenet",
    ) -> Rectifier:
        """From a ``dimenet-model/1`` .onnx file or a bundled model's name (``model.BUNDLED_MODELS``:
        "default", "any-scene"); without a path, the bundled default model.
        ``K_c`` (3, 3) px and ``image_size`` (width, height) px: the camera (OpenCV's pixel
        convention, the centre of the top-left pixel at (0, 0)); a generic model needs both, a
        device model keeps its own camera without them and accepts a rescale or crop of it
        (``image_size`` alone: a rescale). ``dist_coeffs``: the lens's distortion about K_c,
        OpenCV's 4/5/8/12/14 coefficients (the points are then as the distorted image holds
        them; needs K_c). ``threads``: ONNX Runtime's, 1 to ``model.MAX_THREADS``. ``mode``:
        "dimenet" (the paper's method) or "map" (the network's K as a prior, fused with the
        frame's own points). CameraError for a camera the model cannot serve."""
        model = load_model(path, threads=threads, providers=providers)
        camera = _camera(model, K_c, image_size)
        if dist_coeffs is not None:
            if camera is None:
                raise CameraError("dist_coeffs: the distortion is stated about K_c: give K_c (and image_size) with it")
            camera = checked_camera(camera.K, camera.image_size, "camera", dist_coeffs)
        return cls(model, mode, camera)

    def __repr__(self) -> str:
        fx, fy, cx, cy = (float(v) for v in k_params(self.K_c))
        kind = "generic" if self.spec.generic is not None else "device"
        return (
            f"Rectifier(model={self.model.source!r} ({kind}), mode={self.mode!r}, "
            f"K_c=(fx {fx:.2f}, fy {fy:.2f}, cx {cx:.2f}, cy {cy:.2f}) px, "
            f"image_size={self.image_size[0]}x{self.image_size[1]} px"
            f"{', with lens' if self.dist_coeffs is not None else ''})"
        )

    @property
    def spec(self) -> ModelSpec:
        """The model's own spec (a generic model's has no camera: see ``K_c``, ``image_size``)."""
        return self.model.spec

    @property
    def population_K_cov(self) -> Optional[np.ndarray]:
        """(4, 4) px^2, the K_cov of a frame that keeps K_c: the spread of K* - K_c over the model's
        training frames in the camera's pixels (None: the model has none, spec < 1.6)."""
        return self._cam.population_cov_user

    def frame_population_K_cov(self, K_c: Optional[ArrayLike] = None) -> Optional[np.ndarray]:
        """``population_K_cov`` of the camera with a frame's own prior ``K_c`` (3, 3) px, as ``rectify``'s (None: the
        Rectifier's): the K_cov of a frame that keeps that K_c."""
        return self.population_K_cov if K_c is None else self._frame_camera(K_c).population_cov_user

    def k_within_bounds(self, k: np.ndarray, K_c: Optional[ArrayLike] = None) -> bool:
        """The K-bounds rule (``ModelSpec.k_within_bounds``) for k (4,) px in the camera's pixels; ``K_c`` (3, 3) px a
        frame's own prior, as ``rectify``'s (its camera's bounds)."""
        bounds = self.K_bounds if K_c is None else self.spec.for_camera(self._frame_user_camera(K_c)).K_bounds
        return frame_within_bounds(list(k), bounds.tolist())

    def rectify(
        self, points_2d: ArrayLike, points_3d: ArrayLike, *, refine: bool = False, K_c: Optional[ArrayLike] = None
    ) -> Rectification:
        """K and pose of one frame from its correspondences: points_2d (N, 2) px, points_3d (N, 3) mm in {W}
        (or OpenCV's (N, 1, 2) and (N, 1, 3), as cv2.findChessboardCorners returns them).

        Lists and other real dtypes are accepted and cast to float64. Raises InputError for
        unusable input. See the module docstring for the stages and ``rectify.checks`` for the
        rules. ``K_c`` (3, 3) px: this frame's own prior (a platform's per-frame K, e.g. Android's
        LENS_INTRINSIC_CALIBRATION) instead of the Rectifier's, in the same image (and lens); a generic model
        serves it, e_c is measured under it and a refused frame keeps it.
        """
        lap = Lap()
        cam = self._cam if K_c is None else self._frame_camera(K_c)
        exact_map = cam.dist_coeffs is None
        p2_image, p2, p3, invariants_3d = validated_frame(
            cam.image, cam.to_model, points_2d, points_3d, exact_map=exact_map
        )
        lap("validate")
        rvec_c0, tvec_c0 = pnp(p2, p3, cam.K_c)
        lap("pnp_kc")
        feats, e_c = stages.frame_features(cam, p2, p3, rvec_c0, tvec_c0)
        lap("features")
        delta_k = self.model.frame_delta_k(feats)
        lap("model")
        cand, reason = stages.frame_candidate(cam, delta_k, feats, p3, e_c, invariants_3d)
        if reason is None and self.mode == "map":
            cand = stages.frame_map(cam, p2, p3, cand, rvec_c0, tvec_c0)
            lap("map")
        if reason is None and cand.rvec is None:
            reason = stages.frame_pose(p2, p3, cand, cam.k_c, (rvec_c0, tvec_c0))
            lap("pnp_k")
        if refine:
            rvec_c0, tvec_c0 = stages.refined(p2, p3, cam.K_c, rvec_c0, tvec_c0)
            if reason is None and cand.from_pnp:
                cand.rvec, cand.tvec = stages.refined(p2, p3, cand.K, cand.rvec, cand.tvec)
                cand.e, cand.stepped = None, False  # polished to the least-squares pose, as K_c's
            e_c = native.frame_error_and_depth(p2, p3, cam.K_c, rvec_c0, tvec_c0)[0]
            lap("refine")
        cand, reason = check_stage.frame_check(cam, p2, p3, cand, reason, e_c, (rvec_c0, tvec_c0), p2_image, refine)
        lap("check")
        lens = (p2_image, p3, rvec_c0, tvec_c0)
        return stages.frame_result(cam, cand, e_c, lap.timings, reason is not None, lens)

    def _frame_camera(self, K_c: ArrayLike) -> stages.ModelCamera:
        """The model's camera of one frame with its own prior ``K_c`` (3, 3) px (``_frame_user_camera``)."""
        camera = self._frame_user_camera(K_c)
        return stages.ModelCamera.build(self.spec.for_camera(camera, self.model.source), camera)

    def _frame_user_camera(self, K_c: ArrayLike) -> Camera:
        """The camera of one frame with its own prior ``K_c`` (3, 3) px: this Rectifier's image and lens (the lens's
        K stays the one its coefficients were stated about). InputError for a device model, which serves its own
        K_c, and for a K_c no camera has (``checked_camera``'s rules)."""
        if self.spec.generic is None:
            raise InputError(
                f"{self.model.source} is a device model: it serves its own K_c; a frame's own K_c needs a generic "
                "model (the bundled default is one)"
            )
        lens_K = None if self.dist_coeffs is None else self._cam.lens_K
        try:
            return checked_camera(K_c, self.image_size, "the frame's K_c", self.dist_coeffs, lens_K)
        except CameraError as exc:
            raise InputError(str(exc)) from None

    def stream(self, **options):
        """A new ``rectify.stream.Stream``: one recording's K tracked frame by frame (``Stream.update``), its
        state its own, so many streams and threads may share this Rectifier; ``options`` as ``Stream``'s."""
        from dimenet.runtime.rectify.stream import Stream

        return Stream(self, **options)

    def network(
        self, points_2d: ArrayLike, points_3d: ArrayLike, rvec_c0: ArrayLike, tvec_c0: ArrayLike
    ) -> NetworkEstimate:
        """The network's part of ``rectify`` for one frame at a C0 pose the app solved (rvec_c0,
        tvec_c0 (3,) {W}->{C0} under K_c): the feature, Delta K, K and sigma before any fallback rule,
        in the camera's pixels; what the full graph (``export.full_graph``) computes. InputError as
        ``rectify``'s input rules."""
        cam = self._cam
        _, p2, p3, invariants_3d = validated_frame(cam.image, cam.to_model, points_2d, points_3d)
        rvec = real_array(rvec_c0, "rvec_c0", "(3,)", 1, 3)
        tvec = real_array(tvec_c0, "tvec_c0", "(3,)", 1, 3)
        feats, e_c = stages.frame_features(cam, p2, p3, rvec, tvec)
        delta_k = self.model.frame_delta_k(feats)
        k = cam.k_c + delta_k
        sigma = None
        if cam.spec.uncertainty is not None:
            cov = stages.frame_covariance(cam.spec, feats, p3, e_c, invariants_3d)
            sigma = np.sqrt(np.diagonal(cov))
        if cam.pixels is not None:
            k = cam.pixels.k_to_user(k)
            sigma = None if sigma is None else sigma * cam.user_px
        K = k_matrix(k)
        return NetworkEstimate(delta_k=k - k_params(cam.K_c_user), K=K, sigma=sigma, features=feats)

    def rectify_batch(
        self,
        points_2d: ArrayLike,
        points_3d: ArrayLike,
        valid: ArrayLike,
        *,
        infer_mask: Optional[ArrayLike] = None,
        refine: bool = False,
    ) -> BatchRectification:
        """K and pose of B frames: points_2d (B, P, 2) px, points_3d (B, P, 3) mm, valid (B, P) bool.

        The stages of ``rectify`` over all frames at once: features of all frames are computed
        together and the model runs once. Poses and errors use each frame's valid points; K is
        inferred from ``infer_mask`` (B, P), a subset of valid (default: valid). A frame with
        fewer than MIN_POINTS inference points, or no pose from them, falls back to K_c. Same
        results as ``rectify`` frame by frame when infer_mask is valid. Raises InputError naming
        the first unusable frame.
        """
        cam = self._cam
        exact_map = cam.dist_coeffs is None
        fr = validated_batch(cam.image, cam.to_model, points_2d, points_3d, valid, infer_mask, exact_map=exact_map)
        rvec_c0, tvec_c0 = stages.batch_c0_poses(cam, fr)
        infer, poses_i, reasons = stages.batch_inference_poses(cam, fr, rvec_c0, tvec_c0)
        net = network_k(cam.spec, self.model.delta_k, fr.points_2d, fr.points_3d, infer, tuple(poses_i))
        # With K inferred from the valid points, the feature's PMD rows are their residuals under K_c
        # at the C0 pose: their mean norm is e_c, and the uncertainty's PMD statistic.
        pmd_px = net.pmd_norms(fr.mask) if infer is fr.valid else None
        if pmd_px is not None:
            e_c0 = pmd_px
        else:
            e_c0 = mean_reprojection_error(fr.points_2d, fr.points_3d, fr.mask, cam.K_c, rvec_c0, tvec_c0)
        cand = stages.batch_candidates(cam, fr, net, rvec_c0, tvec_c0, e_c0, reasons)
        pending = cand.standing
        if cam.spec.uncertainty is not None:
            stages.batch_covariances(cam, cand, net, fr, infer, pending, pmd_px)
        if self.mode == "map":
            stages.batch_maps(cam, cand, net, fr, infer, poses_i, pending)
        e_c = e_c0  # the C0 pose and K_c on all valid points
        if refine:
            for b, (x, X) in enumerate(fr.frames):
                rvec_c0[b], tvec_c0[b] = stages.refined(x, X, cam.K_c, rvec_c0[b], tvec_c0[b])
                if pending[b] and not cand.from_map[b]:
                    cand.rvec[b], cand.tvec[b] = stages.refined(x, X, cand.K[b], cand.rvec[b], cand.tvec[b])
                    cand.stepped[b] = False
            e_c = mean_reprojection_error(fr.points_2d, fr.points_3d, fr.mask, cam.K_c, rvec_c0, tvec_c0)
        e = check_stage.batch_errors(cam, cand, fr, pending, e_c, (rvec_c0, tvec_c0), (infer, poses_i), refine)
        return stages.batch_result(cam, cand, fr, e, e_c, (rvec_c0, tvec_c0))
