"""K tracked through a recording (``Rectifier.stream()``, `dimenet rectify --points FILE --temporal`).

A ``Stream`` holds one recording's state, apart from the shared ``Rectifier`` (which stays safe for many threads
and streams): a Kalman filter over k = (fx, fy, cx, cy) px. Each frame:

1. predict: an AR(1) process about K_c, per parameter, k' = k_c + a (k - k_c) with a = exp(-dt / tau) (dt from
   ``t_ns``, else one frame at ``frame_s``), and the covariance drawn back towards the stationary spread Q of
   K* - K_c (``Rectifier.population_K_cov``): P' = a P a + (1 - a a) Q (elementwise in a's outer product). The
   principal point's tau is short (the OIS centring loop forgets the hand's motion in a fraction of a second),
   the focal length's long (it moves only when the camera refocuses);
2. the frame's evidence: ``Rectifier.rectify``'s K and K_cov (the network's, or on fallback K_c with the
   population spread: weak evidence towards K_c);
3. events: a cut (the C0-side pose jumps by more than CUT_DEG or CUT_DEPTH of the scene's distance between frames),
   a gap in t_ns (more than GAP_FRAMES frame times) or an innovation beyond INNOVATION_CHI2 (a refocus) resets the
   state to K_c with Q before the update (``StreamFrame.event`` says which);
4. update, then the fused K's pose by PnP over the frame's points, and the same never-worse rule as per frame
   (``checks.loses_to_k_c``): where the fused K fits the frame's points worse than K_c, the frame's result is the
   per-frame one (K_c's or the network's own, which passed it), and the state is kept.

Constant memory: the state is 4 + 16 numbers, the previous pose and time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import frame_error_and_depth, k_matrix, k_params, rvec_to_matrix, undistort_points
from dimenet.runtime.geometry import solve_pnp_start as pnp
from dimenet.runtime.rectify.checks import loses_to_k_c
from dimenet.runtime.rectify.results import Rectification

TAU_S = (30.0, 30.0, 0.6, 0.6)  # AR(1) time constants of fx, fy, cx, cy (s)
FRAME_S = 1.0 / 30.0  # a frame's time when the stream has no t_ns
GAP_FRAMES = 5.0  # a gap of more than this many frame times resets the state
CUT_DEG = 8.0  # the pose turning by more than this between frames is a cut ...
CUT_DEPTH = 0.25  # ... or its distance changing by more than this share
INNOVATION_CHI2 = 30.0  # squared Mahalanobis innovation (4 dof) beyond which the state resets (p ~ 5e-6)
EVENTS = ("start", "cut", "gap", "jump")


@dataclass(frozen=True)
class StreamFrame:
    """One frame of a stream: ``result`` (a Rectification: K the fused K or, where that fits worse than K_c, the
    per-frame result; K_cov the filter's covariance when the fused K stands), ``per_frame`` the frame's own
    ``Rectifier.rectify`` result, ``event`` None or one of EVENTS (the state was reset before this frame),
    ``fused`` whether result.K is the filter's."""

    result: Rectification
    per_frame: Rectification
    event: Optional[str]
    fused: bool


class Stream:
    """One recording's K filter over a shared Rectifier (see the module doc). ``update`` one frame at a time."""

    def __init__(self, rectifier, *, tau_s=TAU_S, frame_s: float = FRAME_S, refine: bool = False) -> None:
        Q = rectifier.population_K_cov
        if Q is None:
            raise InputError(
                f"{rectifier.model.source}: a stream needs a model with an uncertainty model (spec >= 1.6)"
            )
        tau = np.asarray(tau_s, dtype=np.float64)
        if tau.shape != (4,) or not np.all(tau > 0) or not frame_s > 0:
            raise InputError(f"tau_s must be 4 times > 0 s and frame_s > 0 s, got {tau_s!r}, {frame_s!r}")
        self.rectifier, self.refine = rectifier, refine
        self.k_c, self.Q = k_params(rectifier.K_c), np.array(Q, dtype=np.float64)
        self.tau_s, self.frame_s = tau, float(frame_s)
        self.k: Optional[np.ndarray] = None
        self.P: Optional[np.ndarray] = None
        self._t_ns: Optional[int] = None
        self._pose: Optional[tuple] = None

    def _reset(self) -> None:
        self.k, self.P = self.k_c.copy(), self.Q.copy()

    def _predict(self, dt_s: float) -> None:
        a = np.exp(-dt_s / self.tau_s)
        A = np.outer(a, a)
        self.k = self.k_c + a * (self.k - self.k_c)
        self.P = A * self.P + (1.0 - A) * self.Q

    def _event(self, t_ns: Optional[int], res: Rectification) -> tuple[Optional[str], float]:
        """Which event resets the state before this frame (or None), and the time since the last frame (s)."""
        dt_s = self.frame_s if t_ns is None or self._t_ns is None else (t_ns - self._t_ns) * 1e-9
        if self.k is None:
            return "start", dt_s
        if dt_s <= 0 or dt_s > GAP_FRAMES * self.frame_s:
            return "gap", dt_s
        R0, d0 = self._pose
        R1, d1 = rvec_to_matrix(res.rvec), float(np.linalg.norm(res.tvec))
        turn = math.degrees(math.acos(float(np.clip((np.trace(R0.T @ R1) - 1.0) / 2.0, -1.0, 1.0))))
        if turn > CUT_DEG or abs(d1 - d0) > CUT_DEPTH * max(d0, 1e-9):
            return "cut", dt_s
        return None, dt_s

    def update(self, points_2d, points_3d, t_ns: Optional[int] = None) -> StreamFrame:
        """The frame's K fused with the stream's state: points as ``Rectifier.rectify`` takes them; ``t_ns`` the
        frame's time (ns, None: FRAME_S after the last). InputError as ``rectify``'s (the state is left as it was)."""
        rect = self.rectifier
        res = rect.rectify(points_2d, points_3d, refine=self.refine)
        event, dt_s = self._event(t_ns, res)
        if event is not None:
            self._reset()
        else:
            self._predict(dt_s)
        z, R = k_params(res.K), res.K_cov
        if R is None:
            R = self.Q
        S = self.P + R
        innovation = z - self.k
        if event is None and float(innovation @ np.linalg.solve(S, innovation)) > INNOVATION_CHI2:
            event = "jump"
            self._reset()
            S, innovation = self.P + R, z - self.k
        gain = np.linalg.solve(S.T, self.P.T).T  # P S^-1
        self.k = self.k + gain @ innovation
        self.P = (np.eye(4) - gain) @ self.P
        self.P = (self.P + self.P.T) / 2.0
        self._t_ns = t_ns if t_ns is not None else None
        self._pose = (rvec_to_matrix(res.rvec), float(np.linalg.norm(res.tvec)))
        return self._checked(points_2d, points_3d, res, event)

    def _checked(self, points_2d, points_3d, res: Rectification, event: Optional[str]) -> StreamFrame:
        """The fused K's result on the frame's points, or the per-frame result where it fits worse than K_c."""
        rect = self.rectifier
        K = k_matrix(self.k)
        p2 = np.asarray(points_2d, dtype=np.float64).reshape(-1, 2)
        p3 = np.asarray(points_3d, dtype=np.float64).reshape(-1, 3)
        e_c = res.reprojection_error_kc_px
        if rect.dist_coeffs is not None:  # both in the pinhole image of K_c (the lens stated about K_c)
            p2 = undistort_points(p2, rect.K_c, rect.dist_coeffs)
            e_c = frame_error_and_depth(p2, p3, rect.K_c, *pnp(p2, p3, rect.K_c))[0]
        if not rect.k_within_bounds(self.k):
            return StreamFrame(res, res, event, False)
        try:
            rvec, tvec = pnp(p2, p3, K)
        except InputError:
            return StreamFrame(res, res, event, False)
        e, depth = frame_error_and_depth(p2, p3, K, rvec, tvec)
        if depth <= 0 or loses_to_k_c(e, e_c, float(rect.K_c[0, 0])):
            return StreamFrame(res, res, event, False)
        P = self.P.copy()
        fused = replace(
            res,
            K=K,
            rvec=rvec,
            tvec=tvec,
            reprojection_error_px=float(e),
            reprojection_error_kc_px=float(e_c),
            delta_k=self.k - self.k_c,
            fallback=None,
            covariance=lambda: P,
        )
        return StreamFrame(fused, res, event, True)
