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
4. update (where P + R is not positive definite, e.g. a NaN in the frame's K_cov, the state is only carried), then
   the fused K's pose over the frame's points (Gauss-Newton steps from the frame's own pose, as the per-frame pose
   under K; SQPnP where the steps find none or their pose would be refused), and the same never-worse rule as per
   frame (``checks.loses_to_k_c``): where the fused K fits the frame's points worse than K_c (or leaves K_bounds,
   or has no pose), the frame keeps K_c's own solution with the reason as its fallback, and the state is kept.

Steps 1, 3's innovation test and 4's update are one call, ``rectify.stream_filter.stream_step`` (in the compiled
core where it is).

A frame may bring its own K_c (``update(..., K_c=)``: the platform's per-frame K, points format 2): the state is then
K's offset from each frame's K_c, which the AR(1) draws back to 0 and which carries from frame to frame as the
platform's K moves (its bias, not its motion, is what the filter averages); that frame's rectify, e_c, K_bounds and
refused result are under its K_c.

With the gyroscope (``motion``, (G, 4) rows t_ns, gx, gy, gz rad/s in {C}: ``formats.motion``), the principal
point is the OIS loop's prediction from the measured rotation (``rectify.gyro_ois``: the loop's cutoff and gain
learned from the frames' points); with the platform's lens-shift samples instead (``lens_shift``, (G, 3) rows t_ns,
x_shift_px, y_shift_px of the active array, times ``lens_shift_scale`` stream px per active-array px: Android's
STATISTICS_OIS_SAMPLES), K_c's centre plus the shift at the frame's time, its gain learned the same way. The focal
length is the filter's or K_c's, whichever has left less error on the
frames' points (on natural labels the network's f is biased per recording, measured 5-60 px RMS where K_c's is 3-11,
which no filter averages away; on a rig it is right).

Constant memory: the state is 4 + 16 numbers, the previous pose and time (and the gyroscope's bank).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from dimenet.runtime import native
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import k_matrix, k_params, rotation_matrices, undistort_points
from dimenet.runtime.geometry import solve_pnp_start as pnp
from dimenet.runtime.rectify.checks import implausible_reason, loses_to_k_c, worse_reason
from dimenet.runtime.rectify.clock import MAX_T_NS
from dimenet.runtime.rectify.gyro_ois import GyroOis, LensShiftOis
from dimenet.runtime.rectify.results import Fallback, Rectification
from dimenet.runtime.rectify.stream_filter import stream_step

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
    K_c's own solution with a fallback; K_cov the filter's covariance when the fused K stands, else the population
    spread), ``per_frame`` the frame's own
    ``Rectifier.rectify`` result, ``event`` None or one of EVENTS (the state was reset before this frame),
    ``fused`` whether result.K is the filter's."""

    result: Rectification
    per_frame: Rectification
    event: Optional[str]
    fused: bool


def _checked_t_ns(t_ns) -> Optional[int]:
    """A frame's ``t_ns`` as an int (ns), or None; InputError unless it is None or an integer (an int, a numpy integer
    or an integral float, not a bool) of magnitude at most MAX_T_NS."""
    if t_ns is None:
        return None
    if isinstance(t_ns, (int, np.integer, float, np.floating)) and not isinstance(t_ns, bool):
        if isinstance(t_ns, (int, np.integer)) or math.isfinite(t_ns) and float(t_ns).is_integer():
            value = int(t_ns)
            if abs(value) <= MAX_T_NS:
                return value
    raise InputError(f"t_ns must be None or an integer of nanoseconds (|t_ns| <= 2**63 - 1), got {t_ns!r}")


class Stream:
    """One recording's K filter over a shared Rectifier (see the module doc). ``update`` one frame at a time."""

    def __init__(
        self,
        rectifier,
        *,
        tau_s=TAU_S,
        frame_s: float = FRAME_S,
        refine: bool = False,
        motion=None,
        lens_shift=None,
        lens_shift_scale: float = 1.0,
    ) -> None:
        Q = rectifier.population_K_cov
        if Q is None:
            raise InputError(
                f"{rectifier.model.source}: a stream needs a model with an uncertainty model (spec >= 1.6)"
            )
        try:
            tau, frame = np.asarray(tau_s, dtype=np.float64), float(frame_s)
        except (TypeError, ValueError):
            tau, frame = None, math.nan
        if tau is None or tau.shape != (4,) or not np.all(tau > 0) or not 0 < frame < math.inf:
            raise InputError(f"tau_s must be 4 times > 0 s and frame_s a finite time > 0 s, got {tau_s!r}, {frame_s!r}")
        self.rectifier, self.refine = rectifier, refine
        self.k_c, self.Q = k_params(rectifier.K_c), np.array(Q, dtype=np.float64)
        self.tau_s, self.frame_s = tau, frame
        self.k: Optional[np.ndarray] = None
        self.P: Optional[np.ndarray] = None
        self._k0 = self.k_c  # the prior the state was last drawn towards: K_c, or the last frame's own
        self._t_ns: Optional[int] = None
        self._pose: Optional[tuple] = None
        if motion is not None and lens_shift is not None:
            raise InputError("a stream takes the gyroscope's samples or the lens shift's, not both")
        self.gyro = None  # the OIS predictor: the gyroscope's loop or the platform's lens shift
        if motion is not None:
            self.gyro = GyroOis(motion, self.k_c)
        elif lens_shift is not None:
            self.gyro = LensShiftOis(lens_shift, self.k_c, lens_shift_scale)

    def _event(self, t_ns: Optional[int], pose: tuple) -> tuple[Optional[str], float]:
        """Which event resets the state before this frame (or None), and the time since the last frame (s); ``pose``
        the frame's (R (3, 3), distance mm)."""
        dt_s = self.frame_s if t_ns is None or self._t_ns is None else (t_ns - self._t_ns) * 1e-9
        if self.k is None:
            return "start", dt_s
        if dt_s <= 0 or dt_s > GAP_FRAMES * self.frame_s:
            return "gap", dt_s
        R0, d0 = self._pose
        R1, d1 = pose
        cos_turn = (float(np.vdot(R0, R1)) - 1.0) / 2.0  # trace(R0^T R1) = the elementwise products' sum
        turn = math.degrees(math.acos(min(max(cos_turn, -1.0), 1.0)))
        if turn > CUT_DEG or abs(d1 - d0) > CUT_DEPTH * max(d0, 1e-9):
            return "cut", dt_s
        return None, dt_s

    def update(self, points_2d, points_3d, t_ns: Optional[int] = None, *, K_c=None) -> StreamFrame:
        """The frame's K fused with the stream's state: points as ``Rectifier.rectify`` takes them; ``t_ns`` the
        frame's time (an integer of ns, ``_checked_t_ns``; None: FRAME_S after the last); ``K_c`` (3, 3) px this
        frame's own prior, as ``rectify``'s (None: the Rectifier's). InputError as ``rectify``'s, or for a t_ns that
        is no integer (the state is left as it was)."""
        rect = self.rectifier
        t_ns = _checked_t_ns(t_ns)
        if self.gyro is not None and t_ns is None:
            raise InputError("a stream with motion needs each frame's t_ns (on the motion's clock)")
        if self.gyro is not None and K_c is not None:
            raise InputError("a stream with motion tracks K about the camera's one K_c, not a frame's own")
        if self.gyro is not None:
            self.gyro.check_time(t_ns)
        res = rect.rectify(points_2d, points_3d, refine=self.refine, K_c=K_c)
        k0 = self.k_c if K_c is None else k_params(res.K_c)
        pose = (rotation_matrices(np.ravel(res.rvec)), math.hypot(*np.ravel(res.tvec).tolist()))
        event, dt_s = self._event(t_ns, pose)
        R = res.K_cov
        step = stream_step(
            k0 if self.k is None else self.k,
            self.Q if self.P is None else self.P,
            self._k0,
            k0,
            k_params(res.K),
            self.Q if R is None else R,
            self.Q,
            self.tau_s,
            dt_s,
            event is not None,
            INNOVATION_CHI2,
        )
        event = "jump" if step.jumped else event
        self.k, self.P, self._k0 = step.k, step.P, k0
        self._t_ns = t_ns
        self._pose = pose
        if self.gyro is not None:
            self._gyro_c(points_2d, points_3d, event, t_ns, (np.ravel(res.rvec), np.ravel(res.tvec)))
        return self._checked(points_2d, points_3d, res, event, K_c)

    def _gyro_c(self, points_2d, points_3d, event: Optional[str], t_ns: int, pose: tuple) -> None:
        """The principal point from the gyroscope's prediction (``rectify.gyro_ois``) in place of the filter's, the
        loop scored on the frame's points (in the pinhole image of K_c with a lens) from the frame's pose (rvec,
        tvec)."""
        gyro, rect = self.gyro, self.rectifier
        if event in ("cut", "gap"):
            gyro.recentre()
        gyro.advance(t_ns)
        p2 = np.asarray(points_2d, dtype=np.float64).reshape(-1, 2)
        p3 = np.asarray(points_3d, dtype=np.float64).reshape(-1, 3)
        if rect.dist_coeffs is not None:
            p2 = undistort_points(p2, rect.K_c, rect.dist_coeffs)
        gyro.score(p2, p3, self.k[:2], pose)
        c, var = gyro.c()
        self.k = np.r_[self.k[:2] if gyro.f_tracked_wins() else self.k_c[:2], c]
        self.P = self.P.copy()
        self.P[2:, :] = self.P[:, 2:] = 0.0
        self.P[2, 2], self.P[3, 3] = var

    def _k_c_kept(self, res: Rectification, p2, p3, event: Optional[str], reason: Fallback, K_c) -> StreamFrame:
        """The frame's K_c's (``res.K_c``; ``K_c`` the frame's own or None) own solution for a frame whose tracked K
        is refused (the per-frame result when it is K_c's; else the pose under K_c by PnP, e = e_c), with ``reason``;
        K_cov the population spread of K_c's camera (``Rectifier.frame_population_K_cov``). The state is kept."""
        if res.fallback is not None and res.fallback.refusal:
            return StreamFrame(res, res, event, False)
        K0 = res.K_c
        rvec, tvec = pnp(p2, p3, K0)
        Q = self.rectifier.frame_population_K_cov(K_c)
        kept = replace(
            res,
            K=K0.copy(),
            rvec=rvec,
            tvec=tvec,
            reprojection_error_px=res.reprojection_error_kc_px,
            delta_k=np.zeros(4),
            fallback=reason,
            covariance=lambda: Q,
        )
        return StreamFrame(kept, res, event, False)

    def _checked(self, points_2d, points_3d, res: Rectification, event: Optional[str], K_c) -> StreamFrame:
        """The fused K's result on the frame's points, or the per-frame result where it fits worse than the frame's
        K_c (``res.K_c``: ``K_c`` the frame's own, or None: the Rectifier's)."""
        rect, K0 = self.rectifier, res.K_c
        K = k_matrix(self.k)
        p2 = np.asarray(points_2d, dtype=np.float64).reshape(-1, 2)
        p3 = np.asarray(points_3d, dtype=np.float64).reshape(-1, 3)
        e_c = res.reprojection_error_kc_px
        if rect.dist_coeffs is not None:  # both in the pinhole image of the lens's K (the camera's K_c)
            p2 = undistort_points(p2, rect.K_c, rect.dist_coeffs)
            e_c = native.error_at_pnp(p2, p3, K0)
        if not rect.k_within_bounds(self.k, K_c=K_c):
            return self._k_c_kept(res, p2, p3, event, implausible_reason(self.k - self._k0, self.k), K_c)
        f0 = float(K0[0, 0])
        try:  # Gauss-Newton steps from the frame's own pose, as the per-frame pose under K (stages.pose_under)
            rvec, tvec, e, depth = native.pose_under_k(p2, p3, self.k, np.ravel(res.rvec), np.ravel(res.tvec))
            refused = not depth > 0 or loses_to_k_c(e, e_c, f0)
        except InputError:
            refused = True
        if refused:  # SQPnP's pose under the tracked K, and the rules again there
            try:
                rvec, tvec = pnp(p2, p3, K)
            except InputError:
                return self._k_c_kept(res, p2, p3, event, Fallback("no_pose", "no PnP pose under the tracked K"), K_c)
            e, depth = native.frame_error_and_depth(p2, p3, K, rvec, tvec)
            if depth <= 0:
                reason = Fallback("behind_camera", "a point lies behind the camera at the pose under the tracked K")
                return self._k_c_kept(res, p2, p3, event, reason, K_c)
            if loses_to_k_c(e, e_c, f0):
                return self._k_c_kept(res, p2, p3, event, worse_reason(e, e_c, f0), K_c)
        P = self.P.copy()
        fused = replace(
            res,
            K=K,
            rvec=rvec,
            tvec=tvec,
            reprojection_error_px=float(e),
            reprojection_error_kc_px=float(e_c),
            delta_k=self.k - self._k0,
            fallback=None,
            covariance=lambda: P,
        )
        return StreamFrame(fused, res, event, True)
