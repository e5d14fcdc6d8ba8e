"""The check stage of the rectifier (``rectify.stages``): e(K) at the candidate's pose and the fallback rules of
``rectify.checks`` (cheirality, structure, worse than K_c, mismatch, evidence), on one frame (``frame_check``) and on
B frames (``batch_errors``); where they refuse K at the pose of pnp_k's Gauss-Newton steps, again at SQPnP's pose under
K (models_spec/model-v1.md, steps 7-10)."""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from typing import Optional

import numpy as np

from dimenet.runtime import native
from dimenet.runtime.geometry import MIN_STRUCTURE_POINTS, mean_reprojection_error, min_depths, residual_structure
from dimenet.runtime.rectify.checks import (
    BEHIND_REASON,
    STRUCTURE_GATE,
    Frames,
    loses_to_k_c,
    mismatched,
    structure_reason,
    structured,
    unproven,
    unproven_reason,
    worse_reason,
)
from dimenet.runtime.rectify.model_camera import ModelCamera
from dimenet.runtime.rectify.stages import BatchCandidates, Candidate, sqpnp_pose


def frame_structure(cam: ModelCamera, p2, p3, c0_pose) -> Optional[str]:
    """The structure rule on one frame's points (model px) under K_c at its C0 pose ``c0_pose``
    (rvec_c0, tvec_c0): the reason, or None (also for frames of fewer than MIN_STRUCTURE_POINTS
    points, which the test cannot read)."""
    if len(p2) < MIN_STRUCTURE_POINTS:
        return None
    structure = residual_structure(p2, p3, cam.K_c, *c0_pose)
    if not structured(structure, cam.structure_px):
        return None
    return structure_reason(structure, cam.user_px, cam.dist_coeffs is None)


def k_c_solutions(cam: ModelCamera, K, rvec, tvec, c0_pose):
    """Which candidates are K_c's own solution: K (3, 3) or (B, 3, 3) equal to K_c (model px) and the
    pose rvec, tvec (3,) or (B, 3) equal to the C0 pose ``c0_pose`` (as PnP under K_c gives it): bool
    or (B,) bool. Such a candidate's error is e_c to the bit, the worse rule's tie (``checks.worse``),
    which keeps it; measured again through another order of operations, e would differ from e_c in
    the last bits and the tie would go either way (issue 48)."""
    same = np.all(K == cam.K_c, (-2, -1)) & np.all(rvec == c0_pose[0], -1) & np.all(tvec == c0_pose[1], -1)
    return same if np.ndim(same) else bool(same)


def frame_check(
    cam: ModelCamera, p2, p3, cand: Candidate, reason, e_c: float, c0_pose, p2_image, refine: bool = False
) -> tuple:
    """The rules of ``frame_rules`` on the candidate; where they refuse K at the pose of pnp_k's Gauss-Newton steps
    (``cand.stepped``), again at SQPnP's pose under K (``sqpnp_pose``, polished with ``refine``), which two other
    estimators' errors may favour (the steps' least-squares pose against SQPnP's C0 pose); on a refusal (``reason``
    or one of these) K_c's own solution at ``c0_pose``. -> (the candidate standing, the reason or None)."""
    rvec_c0, tvec_c0 = c0_pose
    if reason is None:
        reason = frame_rules(cam, p2, p3, cand, e_c, c0_pose, p2_image)
        pose = sqpnp_pose(p2, p3, cand.K, refine) if reason is not None and cand.stepped else None
        if pose is not None:
            cand = replace(cand, rvec=pose[0], tvec=pose[1], stepped=False, e=None)
            reason = frame_rules(cam, p2, p3, cand, e_c, c0_pose, p2_image)
    if reason is not None:
        covariance = None if cam.population_cov is None else partial(np.array, cam.population_cov)
        zero = np.zeros(4)
        K_c = cam.K_c_user.copy()
        cand = Candidate(K=K_c, delta_k=zero, covariance=covariance, rvec=rvec_c0, tvec=tvec_c0, e=e_c, note=reason)
    return cand, reason


def frame_rules(cam: ModelCamera, p2, p3, cand: Candidate, e_c: float, c0_pose, p2_image) -> Optional[str]:
    """e(K) over the frame's points into ``cand`` (where not measured yet), then the cheirality, worse-than-K_c and
    evidence rules (on the errors the result reports: in the lens's image from ``p2_image`` when the camera has one)
    and, where e(K) is above STRUCTURE_GATE e(K_c), the structure rule at the C0 pose first (its reason says more
    than the worse rule's; the mismatch rule's says more than it); a candidate that is K_c's own solution
    (``k_c_solutions``: Delta K = 0) has e = e_c, a tie. -> the reason K is refused, or None."""
    rvec_c0, tvec_c0 = c0_pose
    own = not np.count_nonzero(cand.delta_k) and k_c_solutions(cam, cand.K, cand.rvec, cand.tvec, c0_pose)
    if own:
        cand.e = e_c
    elif cand.e is None:
        cand.e, depth = native.frame_error_and_depth(p2, p3, cand.K, cand.rvec, cand.tvec)
        if depth <= 0:
            return BEHIND_REASON
    e, e_c_rule = cand.e, e_c
    if cam.dist_coeffs is not None:  # in model px, as fx_c
        K_user = cam.K_c_user if own else cand.K if cam.pixels is None else cam.pixels.K_to_user(cand.K)
        K = np.stack([K_user, cam.K_c_user])
        image = cam.image_errors(p2_image[None], p3[None], None, K, (cand.rvec, rvec_c0), (cand.tvec, tvec_c0))
        e, e_c_rule = image[:, 0] / cam.user_px
    reason = None
    if e > STRUCTURE_GATE * e_c_rule and not mismatched(e, e_c_rule, cam.fx_c):
        reason = frame_structure(cam, p2, p3, c0_pose)
    if reason is None and loses_to_k_c(e, e_c_rule, cam.fx_c):
        reason = worse_reason(e, e_c_rule, cam.fx_c, cam.user_px)
    if reason is None and np.count_nonzero(cand.delta_k) and unproven(e, e_c_rule, len(p2)):
        reason = unproven_reason(e, e_c_rule, len(p2), cam.user_px)
    return reason


def batch_errors(
    cam: ModelCamera, cand: BatchCandidates, fr: Frames, pending, e_c, c0_poses, inference, refine: bool = False
) -> np.ndarray:
    """``batch_rules`` on the pending frames; where they refuse K at the pose of pnp_k's Gauss-Newton steps
    (``cand.stepped``), again at SQPnP's pose under K (``sqpnp_pose``, polished with ``refine``), as a frame's
    ``frame_check``. -> e (B,) px: e(K) at the pose standing (e_c where not pending)."""
    e = batch_rules(cam, cand, fr, pending, e_c, c0_poses, inference)
    again = np.zeros_like(pending)
    for b in np.flatnonzero(pending & cand.stepped & ~cand.standing):
        pose = sqpnp_pose(*fr.frames[b], cand.K[b], refine)
        if pose is not None:
            (cand.rvec[b], cand.tvec[b]), cand.stepped[b], cand.reasons[b], again[b] = pose, False, None, True
    if again.any():
        e[again] = batch_rules(cam, cand, fr, again, e_c, c0_poses, inference)[again]
    return e


def batch_rules(cam: ModelCamera, cand: BatchCandidates, fr: Frames, pending, e_c, c0_poses, inference) -> np.ndarray:
    """e(K) over each frame's valid points (e_c where not pending), and the cheirality, worse-than-K_c,
    evidence and (where e(K) is above STRUCTURE_GATE e(K_c)) structure rules into ``cand.reasons`` (on the
    errors the result reports: in the lens's image when the camera has one, K_c's at the C0 poses
    ``c0_poses`` (rvec_c0, tvec_c0)); the structure rule reads what the network read, ``inference``
    (infer (B, P) bool, (rvec, tvec) their C0 poses)."""
    e = e_c.copy()
    if pending.any():
        mask = None if fr.mask is None else fr.mask[pending]
        behind = min_depths(fr.points_3d[pending], mask, cand.rvec[pending], cand.tvec[pending]) <= 0
        for b in np.flatnonzero(pending)[behind]:
            cand.reasons[b] = BEHIND_REASON
        pending = pending & cand.standing
    own = pending & ~cand.delta_k.any(-1)
    if own.any():  # K_c's own solutions: e = e_c, the worse rule's tie
        own[own] = k_c_solutions(cam, cand.K[own], cand.rvec[own], cand.tvec[own], (c0_poses[0][own], c0_poses[1][own]))
    if (pending & ~own).any():
        rows = pending & ~own
        e[rows] = mean_reprojection_error(
            fr.points_2d[rows],
            fr.points_3d[rows],
            None if fr.mask is None else fr.mask[rows],
            cand.K[rows],
            cand.rvec[rows],
            cand.tvec[rows],
        )
    e_rule, e_c_rule = e, e_c
    if cam.dist_coeffs is not None and pending.any():  # the errors in the lens's image, in model px as fx_c
        e_rule, e_c_rule = e.copy(), e_c.copy()
        rows = np.flatnonzero(pending)
        K_user = cand.K[rows] if cam.pixels is None else cam.pixels.K_to_user(cand.K[rows])
        K_user[own[rows]] = cam.K_c_user
        K = np.stack([K_user, np.broadcast_to(cam.K_c_user, K_user.shape)])
        p3 = np.where(fr.valid[rows, :, None], fr.points_3d[rows], 0.0)
        mask = None if fr.mask is None else fr.mask[rows]
        poses = (cand.rvec[rows], c0_poses[0][rows]), (cand.tvec[rows], c0_poses[1][rows])
        image = cam.image_errors(fr.points_2d_image[rows], p3, mask, K, *poses) / cam.user_px
        e_rule[rows], e_c_rule[rows] = image
    tested = pending & (e_rule > STRUCTURE_GATE * e_c_rule) & ~mismatched(e_rule, e_c_rule, cam.fx_c)
    infer, (rvec_i, tvec_i) = inference
    for b in np.flatnonzero(tested):
        m = infer[b]
        cand.reasons[b] = frame_structure(cam, fr.points_2d[b][m], fr.points_3d[b][m], (rvec_i[b], tvec_i[b]))
    for b in np.flatnonzero(pending & loses_to_k_c(e_rule, e_c_rule, cam.fx_c)):
        if cand.reasons[b] is None:
            cand.reasons[b] = worse_reason(e_rule[b], e_c_rule[b], cam.fx_c, cam.user_px)
    n_points = fr.valid.sum(-1)
    for b in np.flatnonzero(pending & cand.delta_k.any(-1)):
        if cand.reasons[b] is None and unproven(e_rule[b], e_c_rule[b], int(n_points[b])):
            cand.reasons[b] = unproven_reason(e_rule[b], e_c_rule[b], int(n_points[b]), cam.user_px)
    return e
