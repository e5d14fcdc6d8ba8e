"""The rectifier's rules, each written once: what input it accepts and when it falls back to K_c.

Input (``InputError`` naming the problem, and the frame in a batch): real arrays of the right
shape; at least ``MIN_POINTS`` correspondences, of distinct 2D and distinct 3D points; finite
values, 3D coordinates within +-MAX_COORDINATE; 2D points inside the camera's
image; points that fix a pose (not coincident, not collinear); a pose under K_c with
every point in front of the camera.

Fallback (K_c's own solution is returned and the result's ``fallback`` says why): the frame's
points fit K_c worse than any frame the model was made for (mean error e(K_c) above
MAX_KC_ERROR_F times K_c's focal length: wrong correspondences, another camera, resolution or
unit); Delta K not finite or K outside the spec's ``K_bounds`` (``ModelSpec.k_within_bounds``); no
pose under K, or one with a point behind the camera; or e(K) > e(K_c): the predicted K fits the
frame's own points worse than K_c (no margin: a rectified K never fits worse than K_c; a tie, e(K) ==
e(K_c), keeps the candidate, as Delta K = 0 does, K_c's own solution; e and e_c
are the errors the result reports, in the lens's image when the camera has one); or the
mismatch rule: e(K_c) above MISMATCH_KC_ERROR_F f and e(K) above MISMATCH_SHARE e(K_c), a large
error under K_c that the predicted K hardly reduces, which an OIS state does not make (points of
another resolution, K_c of another lens, 3D points in another unit; training/METHOD.md, "Camera
mismatch"); or the structure rule (``structured``): K removes less than half of e(K_c) and the
frame's residuals under K_c hold smooth structure that neither OIS nor corner noise makes, which the
network read as OIS (a sheet that is not flat, a lens K_c leaves out); an OIS shift that K
explains leaves e(K) far below e(K_c), and the test (~100 us) runs only where it does not; or the
evidence rule (``unproven``): e(K) below e(K_c) by no more than fitting K's 4 parameters to the
points' noise gives by chance, so the frame does not show the move (natural labels). A frame
that keeps K_c gets the population covariance as its K_cov when the model has one
(``Uncertainty.population_sigma_px``).

The values in the reasons are in the user's pixels (``user_px``: user px per model px).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

import cv2
import numpy as np

from dimenet.runtime import native
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import (
    MAX_COORDINATE,
    MIN_POINTS,
    ResidualStructure,
    check_not_degenerate,
    covariance_invariants,
    covariance_invariants_batch,
)
from dimenet.runtime.rectify.results import Fallback

# Largest mean error under K_c (at its best pose) a frame may have, as a fraction of K_c's fx:
# 0.006 f is 18 px on the paper's phones, twice the worst of their simulated rig, planar and
# natural frames (8.4 px) and beyond 3 px noise on them; shuffled, flipped or other-camera
# points lie far above (training/METHOD.md, "Runtime safety").
MAX_KC_ERROR_F = 0.006
# The mismatch rule: above this fraction of K_c's fx (9 px at f = 3000 px, beyond every simulated
# rig and planar frame and all but a few natural ones), the predicted K must remove more than
# 1 - MISMATCH_SHARE of e(K_c) (the OIS's share: on the paper's phones e drops 3.3 -> 0.5 px).
MISMATCH_KC_ERROR_F = 0.003
MISMATCH_SHARE = 0.8
# Cheap sufficient test of a spread-out configuration (see clearly_spread): second largest over
# largest eigenvalue of the points' covariance, and the largest over (scale)^2. Far stricter
# than check_not_degenerate's limits, which then decides the frames failing it.
# The structure rule (``structured``; training/METHOD.md, "Residual structure"): a frame whose K
# leaves more than STRUCTURE_GATE of e(K_c) keeps K_c when the smooth structure of its residuals
# under K_c is above the model's residual_structure_px (models before spec 1.6: STRUCTURE_PX,
# model px) with an F statistic above STRUCTURE_RATIO; the reason names the lens when RADIAL_SHARE
# of it or more is radial.
STRUCTURE_GATE = 0.5
STRUCTURE_PX = 0.5
STRUCTURE_RATIO = 3.0
RADIAL_SHARE = 0.5
# The evidence rule (``unproven``): K stands only where the frame's own points show its move with a p-value of
# at most EVIDENCE_P against K_c (training/METHOD.md, "Evidence for a move"); the parameters a frame fits.
EVIDENCE_P = 0.05
POSE_PARAMETERS, K_PARAMETERS = 6, 4
SPREAD_RATIO = 1e-4
SPREAD_ABSOLUTE = 1e-10


def real_array(value, name: str, shape: str, ndim: int, last: int, *, opencv: bool = False) -> np.ndarray:
    """C-contiguous float64 array of ``ndim`` dims ending in ``last`` from any real array-like;
    ``opencv``: (N, 1, last) too (as cv2.findChessboardCorners and cv2.projectPoints return them)."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array of numbers ({exc})") from None
    if a.dtype.kind not in "iuf":
        raise InputError(f"{name}: dtype {a.dtype} cannot be cast to float64 coordinates")
    if opencv and a.ndim == ndim + 1 and a.shape[-2:] == (1, last):
        a = a.reshape(*a.shape[:-2], last)
    if a.ndim != ndim or a.shape[-1] != last:
        raise InputError(f"{name}: expected shape {shape}, got {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float64)


def bool_mask(value, name: str, shape: tuple) -> np.ndarray:
    """A bool array of ``shape`` from bool or integer input, or InputError."""
    a = np.asarray(value)
    if a.dtype.kind not in "biu" or a.shape != shape:
        raise InputError(f"{name}: expected a bool array of shape {shape}, got {a.dtype} {a.shape}")
    return a.astype(bool, copy=False)


class ImageBounds:
    """The camera's image: pixel centres run from 0 to size - 1 (OpenCV), so it
    covers [-0.5, width - 0.5] x [-0.5, height - 0.5] px."""

    def __init__(self, image_size) -> None:
        self.width, self.height = (int(v) for v in image_size)
        self.low = np.array([-0.5, -0.5])
        self.high = np.array([self.width - 0.5, self.height - 0.5])
        self.cv_bounds = (tuple(self.low.tolist()), tuple(self.high.tolist()))  # for cv2.inRange

    def inside(self, points_2d: np.ndarray, points_3d: np.ndarray) -> np.ndarray:
        """(..., N) bool: 3D point within [-MAX_COORDINATE, MAX_COORDINATE) (finite) and 2D point
        inside the image."""
        inside_2d = np.all((points_2d >= self.low) & (points_2d <= self.high), -1)
        return inside_2d & np.all((points_3d >= -MAX_COORDINATE) & (points_3d < MAX_COORDINATE), -1)

    def raise_bad_values(self, points_2d, points_3d, valid, where: str) -> None:
        """InputError naming the first non-finite or outside-the-image point of one frame among
        its ``valid`` ones ((N,) bool, or True for all)."""
        for name, a in (("points_2d", points_2d), ("points_3d", points_3d)):
            bad = valid & ~np.isfinite(a).all(-1)
            if bad.any():
                i = int(np.argmax(bad))
                raise InputError(f"{where}{name}: point {i} is not finite ({a[i].tolist()})")
        far = valid & ~np.all(np.abs(points_3d) < MAX_COORDINATE, -1)
        if far.any():
            i = int(np.argmax(far))
            raise InputError(
                f"{where}points_3d: point {i} at {points_3d[i].tolist()} lies beyond +-{MAX_COORDINATE:g} "
                f"(in the points' unit): not a scene a camera sees"
            )
        i = int(np.argmax(valid & ~self.inside(points_2d, points_3d)))
        raise InputError(
            f"{where}points_2d: point {i} at ({points_2d[i, 0]:.1f}, {points_2d[i, 1]:.1f}) px is "
            f"outside the camera's {self.width}x{self.height} px image"
        )


def too_few_distinct(points_2d: np.ndarray, points_3d: np.ndarray, minimum: int) -> Optional[int]:
    """None when one frame's (N, 2) and (N, 3) points hold at least ``minimum`` distinct 2D and
    distinct 3D points (repeated correspondences add nothing to a pose), else the smaller of the
    two distinct counts. Rows of ``minimum`` distinct x coordinates suffice, so the x of the first
    2 x minimum rows decide an ordinary frame (1 us); only when they repeat are all rows counted."""
    head = 2 * minimum
    if len(set(points_2d[:head, 0].tolist())) >= minimum and len(set(points_3d[:head, 0].tolist())) >= minimum:
        return None
    n = min(len(np.unique(a, axis=0)) for a in (points_2d, points_3d))
    return None if n >= minimum else n


def clearly_spread(trace, minors, scale, dims: int):
    """The points clearly span >= 2 dimensions, from the invariants of their covariance (D = dims
    eigenvalues l1 >= l2 >= ...): trace T = sum l and S the sum of its principal 2x2 minors;
    scale = max(|coordinate|, 1). As l1 <= T and S <= 3 l1 l2, S > 3 SPREAD_RATIO T^2 gives
    l2 > SPREAD_RATIO l1; as l1 >= T / D, T > D SPREAD_ABSOLUTE scale^2 gives l1 > SPREAD_ABSOLUTE
    scale^2. A sufficient condition for ``check_not_degenerate`` to pass. Floats, or (B,) arrays."""
    return (minors > 3 * SPREAD_RATIO * (trace * trace)) & (trace > dims * SPREAD_ABSOLUTE * (scale * scale))


def well_spread(points: np.ndarray, invariants: tuple) -> bool:
    """``clearly_spread`` of one frame's (N, D) finite points, D = 2 or 3, from their
    ``covariance_invariants``."""
    trace, minors, _ = invariants
    return bool(clearly_spread(trace, minors, max(cv2.norm(points, cv2.NORM_INF), 1.0), points.shape[1]))


def check_spread(points_2d: np.ndarray, points_3d: np.ndarray) -> tuple:
    """InputError (from check_not_degenerate) when one frame's points cannot fix a pose; else the
    ``covariance_invariants`` of points_3d (the uncertainty's thickness reads them)."""
    invariants_3d = covariance_invariants(points_3d)
    if not (well_spread(points_3d, invariants_3d) and well_spread(points_2d, covariance_invariants(points_2d))):
        check_not_degenerate(points_2d, points_3d)
    return invariants_3d


def spread_frames(points: np.ndarray, valid: Optional[np.ndarray]) -> tuple[np.ndarray, tuple]:
    """(B, P, D) points (D = 2 or 3) of B frames, valid (B, P) bool or None (all) -> (B,) bool
    ``clearly_spread`` of each frame's valid points, vectorised, and the
    ``covariance_invariants_batch`` it read."""
    where = True if valid is None else valid[..., None]
    scale = np.max(np.abs(points), axis=(1, 2), where=where, initial=1.0)
    invariants = covariance_invariants_batch(points, valid)
    return clearly_spread(invariants[0], invariants[1], scale, points.shape[-1]), invariants


def worse(e, e_c):
    """The worse rule: e(K) strictly above e(K_c), with no margin (training/METHOD.md, "Never worse than
    K_c"). The tie-break: e > e_c is worse, and so is a NaN in either; a tie, e == e_c, is not, so the
    candidate stands (K fits the frame's points as well as K_c). A Delta K of 0 ties: K is K_c and its
    pose the C0 pose, and the rectifier takes its e as e_c rather than measure it again through other
    rounding (``check_stage.k_c_solutions``). floats -> bool, (B,) arrays -> (B,) bool."""
    return np.logical_not(e <= e_c)


def mismatched(e, e_c, fx_c: float):
    """The mismatch rule: e_c (px) above MISMATCH_KC_ERROR_F fx_c and e (px) above MISMATCH_SHARE
    e_c, both strictly (at either equality the rule does not hold): floats -> bool, (B,) arrays -> (B,) bool."""
    return (e_c > MISMATCH_KC_ERROR_F * fx_c) & (e > MISMATCH_SHARE * e_c)


def loses_to_k_c(e, e_c, fx_c: float):
    """The predicted K gives way to K_c's solution: the worse rule or the mismatch rule (e, e_c,
    fx_c in model px): floats -> bool, (B,) arrays -> (B,) bool."""
    return worse(e, e_c) | mismatched(e, e_c, fx_c)


def move_p_value(e: float, e_c: float, n_points: int) -> float:
    """How likely the frame's noise alone makes K look this good: the p-value of the F test of K's 4
    parameters against K_c on the frame's n_points points, with the mean errors' squares e**2 and e_c**2
    (px) in place of the residuals' mean squares. Under K_c with Gaussian noise, e(K) of K fitted to the
    noise gives F = ((e_c^2 - e^2) / 4) / (e^2 / n) with n = 2 n_points - 10 (6 pose + 4 K parameters) on
    F(4, n), whose tail at q = e^2 / e_c^2 is q^(n/2) (1 + (n/2)(1 - q)) (the incomplete beta function
    of an integer parameter, in closed form). 1 when e >= e_c or either is NaN, 0 when e = 0 < e_c."""
    if not e < e_c:
        return 1.0
    q = (e / e_c) ** 2
    if q <= 0.0:  # e = 0, or e / e_c below the smallest float
        return 0.0
    half = n_points - (POSE_PARAMETERS + K_PARAMETERS) / 2.0
    return math.exp(half * math.log(q) + math.log1p(half * (1.0 - q)))


def unproven(e: float, e_c: float, n_points: int) -> bool:
    """The evidence rule: K's lower error e (px) over e_c (px) on the frame's n_points points is within
    what fitting K's parameters to the points' noise gives (``move_p_value`` above EVIDENCE_P): one
    frame does not justify the move, and K_c is kept (training/METHOD.md, "Evidence for a move")."""
    return move_p_value(e, e_c, n_points) > EVIDENCE_P


def unproven_reason(e: float, e_c: float, n_points: int, user_px: float = 1.0) -> Fallback:
    """Why ``unproven`` (e, e_c in model px; the reason in the user's, ``user_px`` per model px)."""
    return Fallback(
        "not_significant",
        f"K_c kept: the predicted K lowers the mean error over the {n_points} points only from "
        f"{e_c * user_px:.3f} to {e * user_px:.3f} px, which fitting K to their noise gives by chance "
        f"(p = {move_p_value(e, e_c, n_points):.2g} > {EVIDENCE_P:g})",
    )


def worse_reason(e: float, e_c: float, fx_c: float, user_px: float = 1.0) -> Fallback:
    """Why ``loses_to_k_c``: the worse rule, else the mismatch rule (e, e_c, fx_c in model px;
    the reason in the user's, ``user_px`` per model px)."""
    if worse(e, e_c):
        return Fallback(
            "worse_than_k_c",
            f"the predicted K fits worse than K_c: {e * user_px:.3f} px vs {e_c * user_px:.3f} px over the points",
        )
    return Fallback(
        "mismatch",
        f"the points do not fit this camera: the predicted K leaves {e * user_px:.1f} of their "
        f"{e_c * user_px:.1f} px mean error under K_c, which an OIS state does not make: points of another "
        f"resolution, K_c of another lens, or 3D points of another scene or unit?",
    )


def implausible_reason(delta_k, k) -> Fallback:
    """Why K = K_c + Delta K was refused: Delta K (4,) px not finite, or k (4,) px (fx, fy, cx, cy,
    in the user's pixels) outside K_bounds."""
    if not np.all(np.isfinite(delta_k)):
        return Fallback("implausible", "the model's Delta K is not finite")
    fx, fy, cx, cy = (float(v) for v in k)
    return Fallback(
        "implausible",
        f"implausible K (fx={fx:.1f}, fy={fy:.1f}, cx={cx:.1f}, cy={cy:.1f} px) outside the model's K_bounds",
    )


def structured(structure: ResidualStructure, limit_px: float) -> bool:
    """The structure rule: the frame's residuals under K_c at the C0 pose hold smooth structure
    (``geometry.residual_structure``, model px) above ``limit_px`` (the spec's
    ``residual_structure_px``, else STRUCTURE_PX) and significant (its F statistic above
    STRUCTURE_RATIO): what neither OIS nor corner noise made in the model's training frames."""
    return structure.amplitude_px > limit_px and structure.ratio > STRUCTURE_RATIO


def structure_reason(structure: ResidualStructure, user_px: float, lens_free: bool) -> Fallback:
    """Why ``structured``, in the user's px (``user_px`` per model px); with a radial share of at
    least RADIAL_SHARE under a camera with no lens (``lens_free``), the lens is named."""
    head = (
        f"K_c kept: the points' residuals under K_c hold {structure.amplitude_px * user_px:.2f} px of smooth "
        f"structure (F = {structure.ratio:.1f}) that neither OIS nor corner noise makes"
    )
    if lens_free and structure.radial_share >= RADIAL_SHARE:
        return Fallback(
            "structure",
            f"{head}, shaped like a radial lens error ({structure.radial_share:.0%} of it): give the camera its "
            f"lens (`dimenet calibrate --distortion opencv5 --camera-out`, or dist_coeffs in the camera file)",
        )
    return Fallback(
        "structure", f"{head}: a sheet that is not flat, a lens K_c leaves out, or a scene unlike the model's?"
    )


def out_of_range(e_c, fx_c: float):
    """The frame's mean error under K_c, e_c (px; float or (B,) array), beyond the model's range
    (MAX_KC_ERROR_F times K_c's fx, px)."""
    return np.logical_not(e_c <= MAX_KC_ERROR_F * fx_c)


def out_of_range_reason(e_c: float, fx_c: float, user_px: float = 1.0) -> Fallback:
    return Fallback(
        "out_of_range",
        f"the points fit K_c with a mean error of {e_c * user_px:.1f} px, beyond the "
        f"{MAX_KC_ERROR_F * fx_c * user_px:.0f} px "
        f"this model was made for: wrong correspondences, or points of another camera, resolution or unit?",
    )


def behind_camera_error(n_behind: int, n: int) -> InputError:
    """The InputError of a frame whose best pose under K_c has points behind the camera."""
    return InputError(
        f"{n_behind} of {n} points lie behind the camera at the best pose under K_c: "
        f"the correspondences do not fit one pinhole camera"
    )


NO_POSE_REASON = Fallback("no_pose", "no pose under the predicted K")
BEHIND_REASON = Fallback("behind_camera", "a point lies behind the camera at the pose under the predicted K")


def all_inside(bounds, points_2d: np.ndarray, points_3d: np.ndarray) -> bool:
    """``bounds.inside(points_2d, points_3d).all()`` (an ``ImageBounds``): (N, 2), (N, 3) float64
    C-contiguous, or any leading dims. OpenCV's checks first (checkRange's range is
    [-MAX_COORDINATE, MAX_COORDINATE), as the reference's), numpy's when they say no: 6 against
    26 µs at 320 points (models_spec/BENCHMARKS.md)."""
    if (
        cv2.checkRange(points_3d, True, -MAX_COORDINATE, MAX_COORDINATE)[0]
        and cv2.countNonZero(cv2.inRange(points_2d.reshape(-1, 1, 2), *bounds.cv_bounds)) == points_2d.size // 2
    ):
        return True
    return bool(bounds.inside(points_2d, points_3d).all())


def check_undistorted(points_model: np.ndarray, points_image: np.ndarray, valid) -> None:
    """InputError naming the first valid point (and its frame, for (B, N, 2) points) whose
    undistortion ``points_model`` is not finite: the lens's model has no inverse there (p1 = p2 = 1,
    say), so no pinhole point, pose or K exists for the frame. ``valid``: (..., N) bool or True."""
    bad = ~np.isfinite(points_model).all(-1) & valid
    if not bad.any():
        return
    where = np.unravel_index(int(np.argmax(bad)), bad.shape)
    x, y = points_image[where]
    frame = f"frame {where[0]}: " if bad.ndim == 2 else ""
    raise InputError(
        f"{frame}points_2d: point {where[-1]} at ({x:.1f}, {y:.1f}) px lies where the lens model has no inverse "
        f"(its undistortion is not finite): the camera's dist_coeffs do not describe the lens there"
    )


def in_frame(b: int, call, *args):
    """``call(*args)``, its InputError prefixed with the frame index ``b`` of a batch."""
    try:
        return call(*args)
    except InputError as exc:
        raise InputError(f"frame {b}: {exc}") from None


def fast_checks(image: ImageBounds, points_2d_image, points_2d, points_3d) -> tuple[int, tuple]:
    """The compiled core's fast tests of one frame (``native.core.frame_checks``, which must be built): 0, or 1 (a
    value not finite, a point outside ``image`` or the coordinate range) or 2 (not clearly spread), for its points
    as given and in the model's pixels (N, 2) px and its (N, 3) mm, float64 C-contiguous; with the
    ``covariance_invariants`` of the 3D points (NaN with 1)."""
    return native.core.frame_checks(
        points_2d_image, points_2d, points_3d, image.width, image.height, MAX_COORDINATE, SPREAD_RATIO, SPREAD_ABSOLUTE
    )


def validated_frame(
    image: ImageBounds, to_model: Callable[[np.ndarray], np.ndarray], points_2d, points_3d, *, exact_map: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
    """The input rules on one frame: its points as float64 (N, 2) px as given, the same mapped by
    ``to_model`` (the user's pixels -> the model's pinhole pixels) before the spread rule, and (N, 3)
    mm, with the ``covariance_invariants`` of the 3D points; or InputError naming the problem.
    ``exact_map``: ``to_model`` raises nothing (no lens), so the compiled core may test the image, the
    range and the spread in one call after it (``native.core.frame_checks``, which also gives the
    invariants; the exact rules decide and word what it refuses)."""
    p2 = real_array(points_2d, "points_2d", "(N, 2) or (N, 1, 2)", 2, 2, opencv=True)
    p3 = real_array(points_3d, "points_3d", "(N, 3) or (N, 1, 3)", 2, 3, opencv=True)
    n = len(p2)
    if len(p3) != n:
        raise InputError(f"points_2d has {n} points and points_3d {len(p3)}: they must correspond one to one")
    if n < MIN_POINTS:
        raise InputError(f"{n} points: rectification needs at least {MIN_POINTS}")
    if exact_map and native.core is not None:
        p2_model = to_model(p2)
        failed, invariants_3d = fast_checks(image, p2, p2_model, p3)
        if failed == 1:
            image.raise_bad_values(p2, p3, True, "")
        if failed == 2:
            check_not_degenerate(p2_model, p3)
        distinct = too_few_distinct(p2_model, p3, MIN_POINTS)
        if distinct is not None:
            raise InputError(f"{distinct} distinct points of {n}: rectification needs at least {MIN_POINTS}")
        return p2, p2_model, p3, invariants_3d
    if not all_inside(image, p2, p3):
        image.raise_bad_values(p2, p3, True, "")
    p2_image, p2 = p2, to_model(p2)
    invariants_3d = check_spread(p2, p3)
    distinct = too_few_distinct(p2, p3, MIN_POINTS)
    if distinct is not None:
        raise InputError(f"{distinct} distinct points of {n}: rectification needs at least {MIN_POINTS}")
    return p2_image, p2, p3, invariants_3d


@dataclass(frozen=True)
class Frames:
    """A validated batch: points_2d (B, P, 2) px (the model's pinhole pixels) and points_3d (B, P, 3)
    mm float64; valid and infer (B, P) bool; mask: valid, or None when every point is valid; frames:
    each frame's valid points; invariants_3d: ``covariance_invariants_batch`` of the valid 3D
    points (None: not computed, the caller's to compute when it needs them); points_2d_image: the points
    as given (the user's pixels, distorted by the lens)."""

    points_2d: np.ndarray
    points_3d: np.ndarray
    valid: np.ndarray
    infer: np.ndarray
    mask: Optional[np.ndarray]
    frames: list
    invariants_3d: Optional[tuple]
    points_2d_image: np.ndarray


def validated_batch(
    image: ImageBounds,
    to_model: Callable[..., np.ndarray],
    points_2d,
    points_3d,
    valid,
    infer_mask,
    *,
    exact_map: bool = False,
) -> Frames:
    """The input rules on B frames (those of ``validated_frame`` on each frame's valid points, and
    infer_mask a subset of valid), the 2D points mapped by ``to_model`` (the user's pixels -> the
    model's pinhole pixels) before the spread rule, or InputError naming the first unusable frame.
    ``exact_map`` (``to_model`` raises nothing): with every point valid, the compiled core tests each
    frame's image, range and spread in one call (``native.core.frame_checks``; the exact rules decide and
    word what it refuses), and the Frames' invariants_3d are left to the caller (None)."""
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
    if exact_map and every and native.core is not None:
        p2_image, p2 = p2, to_model(p2, valid)
        failed = [fast_checks(image, p2_image[b], p2[b], p3[b])[0] for b in range(len(p2))]
        for b in (b for b, f in enumerate(failed) if f == 1):  # the first frame outside, then the first not spread
            image.raise_bad_values(p2_image[b], p3[b], True, f"frame {b}: ")
        for b in (b for b, f in enumerate(failed) if f == 2):
            in_frame(b, check_not_degenerate, p2[b], p3[b])
        frames = [(p2[b], p3[b]) for b in range(len(p2))]
        _check_distinct(frames)
        return Frames(p2, p3, valid, infer, mask, frames, None, p2_image)
    inside = (
        all_inside(image, p2, p3)
        if every
        else all_inside(image, np.where(valid[..., None], p2, 0.0), np.where(valid[..., None], p3, 0.0))
    )
    if not inside:
        for b in np.flatnonzero(np.any(valid & ~image.inside(p2, p3), 1)):
            image.raise_bad_values(p2[b], p3[b], valid[b], f"frame {b}: ")
    p2_image, p2 = p2, to_model(p2, valid)
    frames = [(p2[b], p3[b]) if every else (p2[b][valid[b]], p3[b][valid[b]]) for b in range(len(p2))]
    spread_3d, invariants_3d = spread_frames(p3, mask)
    spread = spread_3d & spread_frames(p2, mask)[0]
    for b in np.flatnonzero(~spread):
        in_frame(b, check_spread, *frames[b])
    _check_distinct(frames)
    return Frames(p2, p3, valid, infer, mask, frames, invariants_3d, p2_image)


def _check_distinct(frames: list) -> None:
    """InputError naming the first of a batch's frames ((x, X) valid points) with too few distinct points."""
    for b, (x, X) in enumerate(frames):
        distinct = too_few_distinct(x, X, MIN_POINTS)
        if distinct is not None:
            raise InputError(
                f"frame {b}: {distinct} distinct valid points of {len(x)}: rectification needs at least {MIN_POINTS}"
            )
