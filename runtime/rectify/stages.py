"""The rectifier's stages after validation, each as a pair: one frame (``frame_*``) and B frames
(``batch_*``) side by side, both keeping the same rule of ``rectify.checks``. The stages run in the
model's pixels (``ModelCamera``); a frame's result comes back in the user's.

The frame path works on plain floats and OpenCV (the hot path); the batch path on (B, ...) arrays.
A batch of one costs about 2.4 times a single frame, so both stay. The check stage (e(K) and the
fallback rules): ``rectify.check_stage``. The camera served: ``rectify.model_camera``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import Callable, Optional

import cv2
import numpy as np

from dimenet.runtime import native
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import (
    MIN_POINTS,
    covariance_invariants,
    frame_mean_norm,
    k_matrix,
    min_depths,
)
from dimenet.runtime.native import solve_pnp_start as pnp
from dimenet.runtime.rectify.checks import (
    NO_POSE_REASON,
    Frames,
    behind_camera_error,
    implausible_reason,
    in_frame,
    out_of_range,
    out_of_range_reason,
)
from dimenet.runtime.rectify.features import grid_features, native_frame_features
from dimenet.runtime.rectify.inference import NetworkK, network_statistics
from dimenet.runtime.rectify.map_fit import map_rectify
from dimenet.runtime.rectify.model_camera import ModelCamera
from dimenet.runtime.rectify.results import BatchRectification, Fallback, Rectification
from dimenet.runtime.rectify.spec import ModelSpec, frame_within_bounds
from dimenet.runtime.rectify.uncertainty import occupied_cells, thickness
from dimenet.runtime.rectify.user_camera import PixelMap


@dataclass
class Candidate:
    """The K on offer for one frame while the stages run: K (3, 3) and delta_k (4,) px; its pose
    {W}->{C} (None until solved), whether pnp_k solved it (refine may polish it) and whether by
    Gauss-Newton steps from the C0 pose (``stepped``: the check tries SQPnP's pose before it refuses
    K); e (px), its mean error over the frame's points (None until measured); covariance: computes
    K_cov (None: none); note: why map's K gave way to DIME-Net's (None otherwise)."""

    K: np.ndarray
    delta_k: np.ndarray
    covariance: Optional[Callable[[], np.ndarray]]
    rvec: Optional[np.ndarray] = None
    tvec: Optional[np.ndarray] = None
    from_pnp: bool = False
    stepped: bool = False
    e: Optional[float] = None
    note: Optional[str] = None


@dataclass
class BatchCandidates:
    """``Candidate`` of B frames: K (B, 3, 3), delta_k (B, 4) px, their poses rvec, tvec (B, 3),
    K_cov (B, 4, 4) px^2 or None; reasons: why each frame's candidate was refused (None:
    standing); notes: map's soft fallbacks; from_map (B,) bool: the pose is the MAP fit's own (not
    PnP's, so refine leaves it, as it does a frame's); stepped (B,) bool: the pose is pnp_k's
    Gauss-Newton steps' (``pose_under``)."""

    K: np.ndarray
    delta_k: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    K_cov: Optional[np.ndarray]
    reasons: list
    notes: list
    from_map: np.ndarray
    stepped: np.ndarray

    @property
    def standing(self) -> np.ndarray:
        return np.array([r is None for r in self.reasons])


def refined(points_2d, points_3d, K, rvec, tvec) -> tuple[np.ndarray, np.ndarray]:
    """cv2.solvePnPRefineLM polish of a pose: least-squares reprojection error under K."""
    r, t = cv2.solvePnPRefineLM(points_3d, points_2d, K, None, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy())
    return r.ravel(), t.ravel()


# -- pnp_kc: the C0 poses under K_c ------------------------------------------------------------


def batch_c0_poses(cam: ModelCamera, fr: Frames) -> tuple[np.ndarray, np.ndarray]:
    """SQPnP poses {W}->{C0} under K_c on each frame's valid points; InputError naming a frame with
    a point behind the camera (a frame's ``frame_features`` checks it from the feature's points)."""
    B = len(fr.frames)
    rvec_c0, tvec_c0 = np.empty((B, 3)), np.empty((B, 3))
    for b, (x, X) in enumerate(fr.frames):
        rvec_c0[b], tvec_c0[b] = in_frame(b, pnp, x, X, cam.K_c)
    behind = min_depths(fr.points_3d, fr.mask, rvec_c0, tvec_c0) <= 0
    if behind.any():
        b = int(np.argmax(behind))
        x, X = fr.frames[b]
        Z = X @ cv2.Rodrigues(rvec_c0[b])[0][2] + tvec_c0[b, 2]
        raise InputError(f"frame {b}: {behind_camera_error(int(np.count_nonzero(Z <= 0)), len(X))}")
    return rvec_c0, tvec_c0


def batch_inference_poses(cam: ModelCamera, fr: Frames, rvec_c0, tvec_c0) -> tuple:
    """The C0 poses of the inference points: the valid points' when they are the inference
    points, else SQPnP under K_c on each frame's inference points; frames with too few of
    them or no pose get a fallback reason and an empty inference mask. -> (infer, (rvec, tvec),
    reasons): the reasons (B,) a new list, which ``batch_candidates`` takes over."""
    reasons: list = [None] * len(fr.frames)
    if fr.infer is fr.valid:
        return fr.infer, (rvec_c0, tvec_c0), reasons
    rvec, tvec, infer = rvec_c0.copy(), tvec_c0.copy(), fr.infer.copy()
    for b in range(len(infer)):
        n = int(infer[b].sum())
        try:
            if n < MIN_POINTS:
                raise InputError(f"{n} inference points, fewer than {MIN_POINTS}")
            rvec[b], tvec[b] = pnp(fr.points_2d[b][infer[b]], fr.points_3d[b][infer[b]], cam.K_c)
        except InputError as exc:
            reasons[b], infer[b] = Fallback("no_k_inferred", f"no K inferred: {exc}"), False
    return infer, (rvec, tvec), reasons


# -- features: the network's input at the C0 pose (a batch's: ``inference.network_k``) ---------


def frame_features(cam: ModelCamera, p2, p3, rvec_c0, tvec_c0) -> tuple[np.ndarray, float]:
    """One frame's grid feature (1, D) at its C0 pose and e_c, its mean error (px) under K_c there
    (the feature's PMD rows); InputError when a point lies behind the camera."""
    if native.core is not None:  # all of it in one call of the compiled core (runtime/native)
        return native_frame_features(p2, p3, cam.K_c, cam.spec.image_size, cam.spec.features, rvec_c0, tvec_c0)
    feats, points = grid_features(
        p2[None],
        p3[None],
        None,
        cam.K_c,
        cam.spec.image_size,
        cam.spec.features,
        poses=(rvec_c0[None], tvec_c0[None]),
        return_points=True,
    )
    if not cv2.checkRange(points[0, 4], True, 0.0, np.inf)[0]:  # 1 / Z_C0 <= 0: a point behind the camera
        raise behind_camera_error(int(np.count_nonzero(points[0, 4] <= 0)), len(p2))
    return feats, frame_mean_norm(points[0, :2])


# -- model's end: the range rule, the K-bounds rule and the network's covariance ----------------


def frame_candidate(cam: ModelCamera, delta_k, feats, points_3d, e_c: float, invariants_3d: Optional[tuple]):
    """(candidate, None), or (None, why) when e_c is beyond the model's range or K = K_c + Delta K
    breaks the K-bounds rule."""
    if out_of_range(e_c, cam.fx_c):
        return None, out_of_range_reason(e_c, cam.fx_c, cam.user_px)
    k = [c + d for c, d in zip(cam.k_c_list, delta_k.tolist())]
    if not frame_within_bounds(k, cam.K_bounds_list):
        return None, implausible_reason(delta_k, cam.user_k(k))
    covariance = None
    if cam.spec.uncertainty is not None:  # computed when K_cov is first asked for: the hot path does not pay
        covariance = partial(frame_covariance, cam.spec, feats, points_3d, e_c, invariants_3d)
    return Candidate(K=k_matrix(k), delta_k=delta_k, covariance=covariance), None


def frame_covariance(spec: ModelSpec, feats: np.ndarray, points_3d, pmd_px: float, invariants_3d=None):
    """The network's 4x4 covariance (px^2) of one frame from its (1, D) feature, its (N, 3) points, mean
    PMD (px) and the ``covariance_invariants`` of its 3D points (None: computed here)."""
    grid, n_channels = feats[0, : spec.features.grid_size], len(spec.features.channels)
    if native.core is not None:  # 0.6 against 6.8 us (models_spec/BENCHMARKS.md); the same count
        cells = native.core.occupied_cells(grid, n_channels)
    else:
        cells = int(occupied_cells(grid[None], n_channels)[0])
    invariants_3d = covariance_invariants(points_3d) if invariants_3d is None else invariants_3d
    return spec.uncertainty.frame_covariance(len(points_3d), cells, pmd_px, thickness(*invariants_3d))


def batch_candidates(cam: ModelCamera, fr: Frames, net: NetworkK, rvec_c0, tvec_c0, e_c0, reasons: list):
    """The range rule on e_c0 (B,) px and the K-bounds rule of B frames, then the pose under each
    standing K on the frame's valid points (``pose_under``). The candidates own the batch's state from here:
    a copy of ``reasons`` (those of ``batch_inference_poses``), which the later stages write, with the notes."""
    reasons = list(reasons)
    cand = BatchCandidates(
        K=k_matrix(net.k),
        delta_k=net.delta_k,
        rvec=rvec_c0.copy(),
        tvec=tvec_c0.copy(),
        K_cov=None,
        reasons=reasons,
        notes=[None] * len(reasons),
        from_map=np.zeros(len(reasons), bool),
        stepped=np.zeros(len(reasons), bool),
    )
    far = out_of_range(e_c0, cam.fx_c)
    for b, (x, X) in enumerate(fr.frames):
        if reasons[b] is None and far[b]:
            reasons[b] = out_of_range_reason(e_c0[b], cam.fx_c, cam.user_px)
        if reasons[b] is None and not net.plausible[b]:
            reasons[b] = implausible_reason(net.delta_k[b], cam.user_k(net.k[b]))
        if reasons[b] is None:
            try:
                pose = pose_under(x, X, net.k[b], net.delta_k[b], (rvec_c0[b], tvec_c0[b]))
            except InputError:
                reasons[b] = NO_POSE_REASON
                continue
            cand.rvec[b], cand.tvec[b], _, cand.stepped[b] = pose
    return cand


def batch_covariances(cam: ModelCamera, cand: BatchCandidates, net, fr: Frames, infer, pending, pmd_px) -> None:
    """The network's K_cov of the pending frames (NaN elsewhere), in place. With K inferred from the
    valid points, validation's 3D invariants and ``pmd_px`` are those of the inference points."""
    cand.K_cov = np.full((len(infer), 4, 4), np.nan)
    if not pending.any():
        return
    features = cam.spec.features
    if pmd_px is not None:
        invariants = None if fr.invariants_3d is None else tuple(a[pending] for a in fr.invariants_3d)
        stats = network_statistics(net, pending, infer, fr.points_3d, features, pmd_px[pending], invariants)
    else:
        stats = network_statistics(net, pending, infer, fr.points_3d, features)
    cand.K_cov[pending] = cam.spec.uncertainty.covariance(stats)


# -- map (mode map): the network's K as a prior fused with the frame's points --------------------


def _map(cam: ModelCamera, p2, p3, k_net: np.ndarray, K_cov_net: np.ndarray, rvec_c0, tvec_c0):
    """(the MAP fit, None), or (None, the note saying why DIME-Net's K stands)."""
    spec = cam.spec
    fit, why = map_rectify(
        p2, p3, k_net, K_cov_net, spec.K_bounds, cam.K_c, pose=(rvec_c0, tvec_c0), uncertainty=spec.uncertainty
    )
    return (fit, None) if why is None else (None, Fallback(why.code, f"map: {why}; DIME-Net's K is returned"))


def frame_map(cam: ModelCamera, p2, p3, cand: Candidate, rvec_c0, tvec_c0) -> Candidate:
    """From the C0 pose (MAP needs no PnP under the network's K): the MAP K, pose and posterior,
    or the DIME-Net candidate with a note."""
    fit, note = _map(cam, p2, p3, cam.k_c + cand.delta_k, cand.covariance(), rvec_c0, tvec_c0)
    if fit is None:
        return replace(cand, note=note)
    return Candidate(
        K=k_matrix(fit.k),
        delta_k=fit.k - cam.k_c,
        covariance=partial(np.array, fit.K_cov),
        rvec=fit.rvec,
        tvec=fit.tvec,
        e=fit.e_px,
    )


def batch_maps(cam: ModelCamera, cand: BatchCandidates, net, fr: Frames, infer, poses_i, pending) -> None:
    """The pending frames' MAP K from their inference points and their C0 pose, in place, and the pose
    on their valid points; a failed fit leaves DIME-Net's K and a note."""
    for b in np.flatnonzero(pending):
        m = infer[b]
        x, X = fr.points_2d[b][m], fr.points_3d[b][m]
        fit, cand.notes[b] = _map(cam, x, X, net.k[b], cand.K_cov[b], poses_i[0][b], poses_i[1][b])
        if fit is not None:
            cand.K[b], cand.delta_k[b], cand.K_cov[b] = k_matrix(fit.k), fit.k - cam.k_c, fit.K_cov
            cand.stepped[b] = False
            if infer is fr.valid:
                cand.rvec[b], cand.tvec[b], cand.from_map[b] = fit.rvec, fit.tvec, True
            else:
                cand.rvec[b], cand.tvec[b] = pnp(*fr.frames[b], cand.K[b])


# -- pnp_k: the pose under the candidate K (a batch's: in ``batch_candidates``) ------------------


def pose_under(p2, p3, k, delta_k, c0_pose) -> tuple:
    """The pose {W}->{C} under K = k_matrix(k) (k (4,) px, K_c + ``delta_k``) of one frame's points (px, mm):
    POSE_STEPS Gauss-Newton steps from the C0 pose ``c0_pose`` (rvec_c0, tvec_c0) (``native.pose_under_k``:
    Delta K is a few px, so the least-squares pose under K is a short step away), or SQPnP under K where the
    steps find none; the C0 pose itself where Delta K = 0 (SQPnP's own under K_c). -> (rvec, tvec, e px at it or
    None where it is not measured (also where a point lies behind the camera there), stepped: whether by the
    steps). InputError when there is no pose."""
    rvec_c0, tvec_c0 = c0_pose
    if not np.count_nonzero(delta_k):
        return rvec_c0.copy(), tvec_c0.copy(), None, False
    try:
        rvec, tvec, e, depth = native.pose_under_k(p2, p3, k, rvec_c0, tvec_c0)
    except InputError:
        return (*pnp(p2, p3, k_matrix(k)), None, False)
    return rvec, tvec, e if depth > 0 else None, True


def frame_pose(p2, p3, cand: Candidate, k_c, c0_pose) -> Optional[str]:
    """The pose under the candidate's K (``pose_under``; k_c (4,) px) into ``cand``; NO_POSE_REASON when there is
    none."""
    try:
        cand.rvec, cand.tvec, cand.e, cand.stepped = pose_under(p2, p3, k_c + cand.delta_k, cand.delta_k, c0_pose)
    except InputError:
        return NO_POSE_REASON
    cand.from_pnp = True
    return None


def sqpnp_pose(p2, p3, K, refine: bool) -> Optional[tuple]:
    """SQPnP's pose under K (3, 3) px (polished by ``refined`` with ``refine``), or None where there is none."""
    try:
        rvec, tvec = pnp(p2, p3, K)
    except InputError:
        return None
    return refined(p2, p3, K, rvec, tvec) if refine else (rvec, tvec)


# -- the result, in the user's pixels -----------------------------------------------------------


def frame_result(cam: ModelCamera, cand: Candidate, e_c: float, timings: dict, fell_back: bool, lens) -> Rectification:
    """The frame's result in the user's pixels (``PixelMap``; the pose is the same in both; on
    fallback K is K_c); ``lens`` (points_2d as given, points_3d, rvec_c0, tvec_c0) puts e and e_c in
    the distorted image when the camera has a lens."""
    pixels, to_user = cam.pixels, cam.user_px
    covariance = cand.covariance
    if covariance is not None and pixels is not None:
        covariance = partial(_covariance_to_user, pixels, covariance)
    K = cand.K
    if fell_back or not np.count_nonzero(cand.delta_k):  # K_c as given (the pixel map's round trip is not exact)
        K = cam.K_c_user.copy()
    elif pixels is not None:
        K = pixels.K_to_user(cand.K)
    e, e_c = cand.e * to_user, e_c * to_user
    if cam.dist_coeffs is not None:
        p2_image, p3, rvec_c0, tvec_c0 = lens
        errors = cam.image_errors(
            p2_image[None], p3[None], None, np.stack([K, cam.K_c_user]), (cand.rvec, rvec_c0), (cand.tvec, tvec_c0)
        )
        e, e_c = float(errors[0, 0]), float(errors[1, 0])
    delta_k = cand.delta_k * to_user if pixels is not None else cand.delta_k
    return Rectification(K, cand.rvec, cand.tvec, e, e_c, delta_k, cand.note, timings, cam.K_c_user, covariance)


def _covariance_to_user(pixels: PixelMap, covariance: Callable[[], np.ndarray]) -> np.ndarray:
    return pixels.covariance_to_user(covariance())


def batch_result(cam: ModelCamera, cand: BatchCandidates, fr: Frames, e, e_c, c0_poses) -> BatchRectification:
    """B frames' result in the user's pixels: fallen-back frames (``cand.reasons``) get K_c's own
    solution at their C0 pose ``c0_poses`` (rvec_c0, tvec_c0); e and e_c in the distorted image
    when the camera has a lens."""
    rvec_c0, tvec_c0 = c0_poses
    fell_back = ~cand.standing
    k_c = fell_back | ~cand.delta_k.any(-1)  # K is K_c: K_c as given (the pixel map's round trip is not exact)
    cand.rvec[fell_back], cand.tvec[fell_back], e[fell_back] = rvec_c0[fell_back], tvec_c0[fell_back], e_c[fell_back]
    K, delta_k, K_cov = cand.K, cand.delta_k, cand.K_cov
    if cam.pixels is not None:
        K, delta_k, e, e_c = cam.pixels.K_to_user(K), delta_k * cam.user_px, e * cam.user_px, e_c * cam.user_px
        K_cov = None if K_cov is None else cam.pixels.covariance_to_user(K_cov)
    K[k_c], delta_k[fell_back] = cam.K_c_user, 0.0
    if K_cov is not None:
        K_cov[fell_back] = np.nan if cam.population_cov_user is None else cam.population_cov_user
    if cam.dist_coeffs is not None:
        p3 = np.where(fr.valid[..., None], fr.points_3d, 0.0)
        K_cs = np.broadcast_to(cam.K_c_user, K.shape)
        e, e_c = cam.image_errors(
            fr.points_2d_image, p3, fr.mask, np.stack([K, K_cs]), (cand.rvec, rvec_c0), (cand.tvec, tvec_c0)
        )
    return BatchRectification(
        K=K,
        rvec=cand.rvec,
        tvec=cand.tvec,
        reprojection_error_px=e,
        reprojection_error_kc_px=e_c,
        delta_k=delta_k,
        fallback=tuple(r if r is not None else n for r, n in zip(cand.reasons, cand.notes)),
        K_c=cam.K_c_user,
        K_cov=K_cov,
    )
