"""The gyroscope's prediction of the OIS lens shift, for a ``rectify.stream.Stream`` given the motion
(`dimenet rectify --points FILE --temporal --motion GYRO.csv`; models_spec/points-csv.md, "Motion").

An OIS loop moves the lens against the hand's rotation by a high-pass of that rotation (its centring filter), times
a gain, so the principal point is c = c_rest + g f (tan hp(yaw), -tan hp(pitch)) in OpenCV {C} (x right, y down):
a turn to the right (+yaw about y) moves the image left, the lens moves c right. c_rest is K_c's centre (the
factory calibration, OIS at rest). The network cannot see this motion (OIS cancels exactly the motion it causes),
so its c is no evidence of the loop; the frame's own points are, summed over many frames.

``GyroOis`` runs, at the gyroscope's own rate, the high-pass of the integrated rates (yaw, pitch) for each cutoff
of a bank (CUTOFFS_HZ), after subtracting the gyroscope's bias (its running mean: cumulative over the first
BIAS_TAU_S, then exponential; what a bias leaves after the high-pass is a small constant). Each (cutoff, gain) pair
of the bank (x GAINS) is scored by the mean reprojection error its K leaves on the frame's points (pose by PnP),
every SCORE_EVERY-th frame (the pose under each K by Gauss-Newton steps from the frame's own), with a forgetting
factor: the loop is the best-scored pair, learned from the frames,
not assumed. The focal length is K_c's or the stream's tracked one, whichever has left less error with the loop's
c (the network's f is biased on some recordings, and right on others). sigma of c: SIGMA_FLOOR_PX and the spread
of the best few pairs' predictions.

``LensShiftOis`` takes the platform's own samples of the lens shift instead (Android's STATISTICS_OIS_SAMPLES: the
optical centre's shift, px of the active array, timestamped): c = c_rest + gain · scale · shift(t), the shift
interpolated at the frame's time, ``scale`` the stream's px per active-array px; the gain (GAINS: the Hall sensor's
calibration as users report it; 0: the samples do not move c) is learned from the frames as the gyroscope's loop is.

Memory: a few numbers per cutoff and pair, and an index into the samples.
"""

from __future__ import annotations

import math

import numpy as np

from dimenet.runtime import native
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import k_matrix

CUTOFFS_HZ = (0.3, 0.5, 0.8, 1.1, 1.5, 2.0)
GAINS = (0.0, 0.8, 0.9, 1.0, 1.1)  # 0: no OIS (off, or a camera without it): c stays K_c's
BIAS_TAU_S = 5.0  # the gyroscope bias's running mean
SCORE_EVERY = 3  # frames between two scorings of the bank (each scoring: one PnP per pair)
SCORE_MEMORY = 0.99  # forgetting factor of the scores, per scoring
MAX_RATE_RAD_S = 100.0  # |rate| above this is no hand-held phone's (a unit error: deg/s)
MAX_SHIFT_PX = 10_000.0  # |lens shift| above this is no lens's (a unit error, or not pixels)
MAX_SCALE = 16.0  # stream px per active-array px: a stream is at most this much finer than the sensor's array
SIGMA_FLOOR_PX = 3.0  # c's sigma floor: the loop's model error (tan, bias, the stroke's clip)
SPREAD_PAIRS = 3  # c's sigma adds the spread of the best few pairs' predictions
MAX_OUTSIDE_S = 60.0  # a frame further than this outside the samples' span: the samples are on another clock
# (boot time against Unix time, another recording's); a sensor started late or stopped early stays within it


def _samples(samples, columns: str, bound: float) -> np.ndarray:
    """(G, C) float64 of ``samples``, G >= 2 rows of ``columns`` (C names) with t_ns increasing and every value
    after t_ns finite and within +-``bound``, or InputError."""
    try:
        samples = np.asarray(samples, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"motion: not an array of numbers ({exc})") from None
    n = len(columns.split(", "))
    if samples.ndim != 2 or samples.shape[1] != n or len(samples) < 2:
        raise InputError(f"motion must be (G >= 2, {n}) rows of {columns} with t_ns increasing, got {samples.shape}")
    if not np.all(np.isfinite(samples[:, 0])) or np.any(np.diff(samples[:, 0]) <= 0):
        raise InputError(f"motion must be (G >= 2, {n}) rows of {columns} with t_ns increasing")
    if not np.all(np.abs(samples[:, 1:]) <= bound):  # NaN fails too
        raise InputError(f"motion: every sample's {columns.split(', ', 1)[1]} must be finite, within +-{bound:g}")
    return samples


def _error(points_2d: np.ndarray, points_3d: np.ndarray, k: np.ndarray, pose: tuple) -> float:
    """The mean reprojection error (px) under k (4,) px at its pose: two Gauss-Newton steps from ``pose`` (the frame's
    own: a pair's c is a few px from it), SQPnP's pose where the steps find none. InputError when there is no pose."""
    try:
        return native.pose_under_k(points_2d, points_3d, k, *pose)[2]
    except InputError:
        return native.error_at_pnp(points_2d, points_3d, k_matrix(k))


class _LoopBank:
    """The scoring both predictors share: rows of lens shifts at gain 1 (``_shifts``) times GAINS, each pair scored
    on the frames' points; ``k_c`` (4,) px."""

    def __init__(self, k_c: np.ndarray, rows: int) -> None:
        self.k_c = np.asarray(k_c, dtype=np.float64)
        self._scores = np.zeros((rows, len(GAINS)))
        self._f_scores = np.zeros(2)  # K_c's f, the tracked f
        self._frames = 0

    def _shifts(self) -> np.ndarray:
        raise NotImplementedError

    def check_time(self, t_ns: int) -> None:
        """InputError when a frame's ``t_ns`` lies more than MAX_OUTSIDE_S outside the samples' span (``samples``: the
        subclass's, t_ns first): samples on another clock than the points', or of another recording, would leave c
        at K_c's or at a stale shift without a word."""
        first, last = self.samples[0, 0], self.samples[-1, 0]
        outside_s = max(first - t_ns, t_ns - last, 0.0) * 1e-9
        if outside_s > MAX_OUTSIDE_S:
            raise InputError(
                f"the frame at t_ns {t_ns} lies {outside_s:.3g} s outside the motion's samples (t_ns {first:.0f} to "
                f"{last:.0f}): the motion must be on the points' clock, of the same recording"
            )

    def _pair_ks(self) -> np.ndarray:
        """(rows, GAINS, 4) px every pair's k: K_c's f, its c plus the gain times the row's shift."""
        ks = np.empty(self._scores.shape + (4,))
        ks[..., :2] = self.k_c[:2]
        ks[..., 2:] = self.k_c[2:] + np.asarray(GAINS)[:, None] * self._shifts()[:, None, :]
        return ks

    def score(self, points_2d: np.ndarray, points_3d: np.ndarray, f_tracked: np.ndarray, pose: tuple) -> None:
        """Score the bank on one frame's points (px, mm), every SCORE_EVERY-th call, with K_c's (fx, fy); then the
        best pair's c with ``f_tracked`` (2,) px (the stream's filter) against it. Each K's error is at its pose by
        ``_error`` from ``pose`` (rvec, tvec (3,)), the frame's own."""
        self._frames += 1
        if (self._frames - 1) % SCORE_EVERY:
            return
        ks = self._pair_ks()
        errors = np.empty_like(self._scores)
        for i, j in np.ndindex(errors.shape):
            if GAINS[j] == 0.0 and i:  # no OIS: the same K at every cutoff
                errors[i, j] = errors[0, j]
                continue
            try:
                errors[i, j] = _error(points_2d, points_3d, ks[i, j], pose)
            except InputError:
                errors[i, j] = np.nan
        if not np.all(np.isfinite(errors)):
            return
        self._scores = SCORE_MEMORY * self._scores + errors
        i, j = np.unravel_index(int(np.argmin(self._scores)), self._scores.shape)
        k = ks[i, j]
        k[:2] = f_tracked
        try:
            e = _error(points_2d, points_3d, k, pose)
        except InputError:
            return
        self._f_scores = SCORE_MEMORY * self._f_scores + (errors[i, j], e)

    def f_tracked_wins(self) -> bool:
        """Whether the tracked f has left less error on the frames' points than K_c's with the loop's c."""
        return bool(self._f_scores[1] < self._f_scores[0])

    def c(self) -> tuple[np.ndarray, np.ndarray]:
        """(cx, cy) px of the best-scored loop now, and their variances (2,) px^2."""
        order = np.argsort(self._scores, axis=None)[:SPREAD_PAIRS]
        preds = self._pair_ks()[..., 2:].reshape(-1, 2)[order]
        return preds[0], SIGMA_FLOOR_PX**2 + preds.var(0)


class GyroOis(_LoopBank):
    """The OIS shift predicted from the gyroscope (see the module doc). ``samples`` (G, 4): t_ns, gx, gy, gz rad/s
    in {C}, t_ns increasing; ``k_c`` (4,) px."""

    def __init__(self, samples, k_c: np.ndarray) -> None:
        super().__init__(k_c, len(CUTOFFS_HZ))
        self.samples = _samples(samples, "t_ns, gx, gy, gz", MAX_RATE_RAD_S)
        self._next = 0  # the first sample not consumed
        self._bias = (0.0, 0.0, 0.0)
        self._bias_s = 0.0
        self._hp = ((0.0, 0.0),) * len(CUTOFFS_HZ)  # (yaw, pitch) high-passed, rad, per cutoff

    def recentre(self) -> None:
        """The OIS recentres (a cut): the high-pass states to 0; the loop's scores stay (the same phone)."""
        self._hp = ((0.0, 0.0),) * len(CUTOFFS_HZ)

    def advance(self, t_ns: int) -> None:
        """Consume the samples up to ``t_ns``: the bias's running mean and the bank's high-pass at the gyro's rate,
        in Python floats (a sample's dozen products cost less so than as numpy's small arrays; CHANGELOG 0.9.5)."""
        s = self.samples
        while self._next < len(s) and s[self._next, 0] <= t_ns:
            i = self._next
            self._next += 1
            if i == 0:
                continue
            step_s = float((s[i, 0] - s[i - 1, 0]) * 1e-9)
            self._bias_s += step_s
            w = min(1.0, step_s / min(self._bias_s, BIAS_TAU_S))
            rates = s[i, 1:].tolist()
            bx, by, bz = (b + w * (g - b) for b, g in zip(self._bias, rates))
            self._bias = (bx, by, bz)
            pitch_rate, yaw_rate = rates[0] - bx, rates[1] - by  # about x and y
            hp = []
            for cutoff, (yaw, pitch) in zip(CUTOFFS_HZ, self._hp):
                a = 1.0 / (1.0 + 2.0 * math.pi * cutoff * step_s)
                hp.append((a * (yaw + yaw_rate * step_s), a * (pitch + pitch_rate * step_s)))
            self._hp = tuple(hp)

    def _shifts(self) -> np.ndarray:
        """(cutoffs, 2) px the lens shift of each cutoff at gain 1."""
        hp = np.array(self._hp)
        return self.k_c[0] * np.stack([np.tan(hp[:, 0]), -np.tan(hp[:, 1])], 1)

    def loop(self) -> dict:
        """The loop as estimated: cutoff (Hz), gain, the gyroscope's bias (rad/s)."""
        i, j = np.unravel_index(int(np.argmin(self._scores)), self._scores.shape)
        return {"cutoff_hz": CUTOFFS_HZ[i], "gain": GAINS[j], "bias_rad_s": list(self._bias)}


class LensShiftOis(_LoopBank):
    """The OIS shift the platform samples (see the module doc). ``samples`` (G, 3): t_ns, x_shift_px, y_shift_px (the
    optical centre's shift, px of the active array: +x to the right, +y down), t_ns increasing; ``k_c`` (4,) px;
    ``scale`` the stream's px per active-array px (> 0)."""

    def __init__(self, samples, k_c: np.ndarray, scale: float = 1.0) -> None:
        super().__init__(k_c, 1)
        self.samples = _samples(samples, "t_ns, x_shift_px, y_shift_px", MAX_SHIFT_PX)
        try:
            self.scale = float(scale)
        except (TypeError, ValueError):
            self.scale = math.nan
        if not 0.0 < self.scale <= MAX_SCALE:
            raise InputError(
                f"the lens shift's scale must be in (0, {MAX_SCALE:g}] stream px per active-array px, got {scale!r}"
            )
        self._shift = np.zeros(2)

    def recentre(self) -> None:
        """The samples are the lens's position itself: nothing to reset at a cut."""

    def advance(self, t_ns: int) -> None:
        """The shift at ``t_ns``, linear between the samples around it (the first or last one outside them)."""
        s = self.samples
        self._shift = np.array([np.interp(float(t_ns), s[:, 0], s[:, 1]), np.interp(float(t_ns), s[:, 0], s[:, 2])])

    def _shifts(self) -> np.ndarray:
        return (self.scale * self._shift)[None]

    def loop(self) -> dict:
        """The shift's gain as estimated and the scale given."""
        return {"gain": GAINS[int(np.argmin(self._scores[0]))], "scale": self.scale}
