"""Per-frame K rectification at run time: 2D-3D correspondences -> K, pose {W}->{C}.

numpy, OpenCV and ONNX Runtime only. Pipeline of one frame (``Rectifier.rectify``), with the
stage names of ``timings_us``:

1. ``validate``: shapes, casts, >= 6 points, finite values, 2D points inside the image the
   model was trained for, a non-degenerate configuration;
2. ``pnp_kc``: SQPnP pose {W}->{C0} under the prior K_c;
3. ``features``: the grid feature (``dimenet.runtime.rectify.features.grid_features``) at that pose;
4. ``model``: one ONNX Runtime call, Delta K (px); K = K_c + Delta K (and its covariance);
5. ``pnp_k``: SQPnP pose under K at native resolution;
6. ``refine`` (only with ``refine=True``): cv2.solvePnPRefineLM polish of both poses;
7. ``check``: mean reprojection errors e(K) and e(K_c) over the given points, fallback rules.

With a model whose spec carries the uncertainty model (spec >= 1.1), ``K_cov`` is the
network's 4x4 covariance of (fx, fy, cx, cy) (px^2) for the frame. In ``mode="map"`` a stage
``map`` replaces ``pnp_k``: the MAP fusion of that prior with the frame's points
(``dimenet.runtime.rectify.map_fit``, from the C0 pose turned to the network's principal point),
whose K, pose and posterior ``K_cov`` are returned; when it fails its checks, the DIME-Net
solution (``pnp_k`` then runs) stands and ``fallback`` says why.

Fallback (the result is then K_c's own solution, Delta K = 0, and ``fallback`` says why):
Delta K not finite; K outside the spec's ``K_bounds``; no pose under K; or
e(K) > (1 + WORSE_RELATIVE) e(K_c) + WORSE_ABSOLUTE_PX, i.e. the predicted K fits the
frame's own points worse than K_c by more than 5 % + 0.05 px.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property, partial
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from dimenet.runtime.assets import asset
from dimenet.runtime.errors import InputError, ModelError
from dimenet.runtime.geometry import (
    check_not_degenerate,
    covariance_invariants,
    covariance_invariants_batch,
    frame_k_matrix,
    frame_residuals,
    k_matrix,
    k_params,
    mean_reprojection_errors,
    mean_residual_norms,
    rotation_matrices,
    solve_pnp_start,
)
from dimenet.runtime.rectify.features import grid_features
from dimenet.runtime.rectify.map_fit import map_rectify
from dimenet.runtime.rectify.model import OnnxModel, load_onnx_model, onnx_model_from_bytes
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.uncertainty import input_statistics, occupied_cells, thickness

MIN_POINTS = 6
WORSE_RELATIVE = 0.05
WORSE_ABSOLUTE_PX = 0.05
DEFAULT_MODEL = "default_model.onnx"
MODES = ("dimenet", "map")
# Cheap sufficient test of a spread-out configuration (see _clearly_spread): second largest over
# largest eigenvalue of the points' covariance, and the largest over (scale)^2. Far stricter
# than check_not_degenerate's limits, which then decides the frames failing it.
SPREAD_RATIO = 1e-4
SPREAD_ABSOLUTE = 1e-10


@dataclass(frozen=True)
class Rectification:
    """One frame. K (3, 3) px; rvec (3,) rad and tvec (3,) mm {W}->{C} under K; the mean Euclidean
    reprojection errors (px) over the given points under K and under K_c (each with its own
    pose); delta_k (4,) px the applied (dfx, dfy, dcx, dcy), 0 on fallback; fallback None or
    why K_c's solution (or in map mode, DIME-Net's) was returned; timings_us: microseconds per
    stage; K_cov (4, 4) px^2 the covariance of (fx, fy, cx, cy): the network's (mode dimenet)
    or the MAP posterior (mode map); None when K is K_c's or the model has no uncertainty.
    ``covariance`` computes K_cov when first asked for: the hot path does not pay for it."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error_px: float
    reprojection_error_kc_px: float
    delta_k: np.ndarray
    fallback: Optional[str]
    timings_us: dict
    covariance: Optional[Callable[[], np.ndarray]] = field(default=None, repr=False, compare=False)

    @cached_property
    def K_cov(self) -> Optional[np.ndarray]:
        """(4, 4) px^2, computed on first access from ``covariance`` (None without one)."""
        return None if self.covariance is None else self.covariance()


@dataclass(frozen=True)
class BatchRectification:
    """B frames, as Rectification: K (B, 3, 3), rvec (B, 3), tvec (B, 3), errors (B,) px over
    each frame's valid points, delta_k (B, 4) px, fallback: one reason or None per frame;
    K_cov (B, 4, 4) px^2, NaN for frames whose K is K_c's, or None without an uncertainty model."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error_px: np.ndarray
    reprojection_error_kc_px: np.ndarray
    delta_k: np.ndarray
    fallback: tuple
    K_cov: Optional[np.ndarray] = None


def _real_array(value, name: str, shape: str, ndim: int, last: int) -> np.ndarray:
    """C-contiguous float64 array of ``ndim`` dims ending in ``last`` from any real array-like."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array of numbers ({exc})") from None
    if a.dtype.kind not in "iuf":
        raise InputError(f"{name}: dtype {a.dtype} cannot be cast to float64 coordinates")
    if a.ndim != ndim or a.shape[-1] != last:
        raise InputError(f"{name}: expected shape {shape}, got {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float64)


def _bool_mask(value, name: str, shape: tuple) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in "biu" or a.shape != shape:
        raise InputError(f"{name}: expected a bool array of shape {shape}, got {a.dtype} {a.shape}")
    return a.astype(bool, copy=False)


def _clearly_spread(trace, minors, scale, dims: int):
    """The points clearly span >= 2 dimensions, from the invariants of their covariance (D = dims
    eigenvalues l1 >= l2 >= ...): trace T = sum l and S the sum of its principal 2x2 minors;
    scale = max(|coordinate|, 1). As l1 <= T and S <= 3 l1 l2, S > 3 SPREAD_RATIO T^2 gives
    l2 > SPREAD_RATIO l1; as l1 >= T / D, T > D SPREAD_ABSOLUTE scale^2 gives l1 > SPREAD_ABSOLUTE
    scale^2. A sufficient condition for ``check_not_degenerate`` to pass. Floats, or (B,) arrays."""
    return (minors > 3 * SPREAD_RATIO * trace**2) & (trace > dims * SPREAD_ABSOLUTE * scale**2)


def _well_spread(points: np.ndarray, invariants: tuple) -> bool:
    """``_clearly_spread`` of one frame's (N, D) finite points, D = 2 or 3, from their
    ``covariance_invariants``."""
    trace, minors, _ = invariants
    return bool(_clearly_spread(trace, minors, max(cv2.norm(points, cv2.NORM_INF), 1.0), points.shape[1]))


def _check_spread(points_2d: np.ndarray, points_3d: np.ndarray) -> tuple:
    """InputError (from check_not_degenerate) when the points cannot fix a pose; else the
    ``covariance_invariants`` of points_3d (the uncertainty's thickness reads them)."""
    invariants_3d = covariance_invariants(points_3d)
    if not (_well_spread(points_3d, invariants_3d) and _well_spread(points_2d, covariance_invariants(points_2d))):
        check_not_degenerate(points_3d, points_2d)
    return invariants_3d


def _spread_frames(points: np.ndarray, valid: Optional[np.ndarray]) -> tuple[np.ndarray, tuple]:
    """(B, P, D) points (D = 2 or 3) of B frames, valid (B, P) bool or None (all) -> (B,) bool
    ``_well_spread`` of each frame's valid points, vectorised, and the
    ``covariance_invariants_batch`` it read."""
    where = True if valid is None else valid[..., None]
    scale = np.max(np.abs(points), axis=(1, 2), where=where, initial=1.0)
    invariants = covariance_invariants_batch(points, valid)
    return _clearly_spread(invariants[0], invariants[1], scale, points.shape[-1]), invariants


def _sqpnp(points_2d: np.ndarray, points_3d: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SQPnP pose {W}->{C} (rvec, tvec (3,)); InputError when there is none."""
    try:
        return solve_pnp_start(points_2d, points_3d, K)
    except cv2.error as exc:
        raise InputError(f"PnP failed: OpenCV could not solve for a pose ({exc.err})") from None


def _refine(points_2d, points_3d, K, rvec, tvec) -> tuple[np.ndarray, np.ndarray]:
    """cv2.solvePnPRefineLM polish of a pose: least-squares reprojection error under K."""
    r, t = cv2.solvePnPRefineLM(points_3d, points_2d, K, None, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy())
    return r.ravel(), t.ravel()


def _mean_error(points_2d, points_3d, K, rvec, tvec) -> float:
    """Mean Euclidean reprojection error (px) of one frame's (N, 2) px / (N, 3) mm points."""
    return _mean_norm(frame_residuals(points_2d, points_3d, K, cv2.Rodrigues(rvec)[0], tvec).T)


def _mean_norm(residuals: np.ndarray) -> float:
    """Mean Euclidean norm (px) of one frame's (2, N) residuals (u row, v row); OpenCV's two calls
    cost half of numpy's three on the hot path."""
    return cv2.sumElems(cv2.magnitude(residuals[0], residuals[1]))[0] / residuals.shape[1]


def _worst_allowed(e_c):
    """The fallback margin: the largest e(K) (px) accepted next to e(K_c), 5 % + 0.05 px above it."""
    return (1.0 + WORSE_RELATIVE) * e_c + WORSE_ABSOLUTE_PX


def _worse(e: np.ndarray, e_c: np.ndarray) -> np.ndarray:
    """(B,) bool: e(K) beyond the fallback margin (a NaN counts as worse)."""
    return np.logical_not(e <= _worst_allowed(e_c))


def _worse_one(e: float, e_c: float) -> bool:
    """``_worse`` of one frame's errors (Python floats, no numpy on the single-frame path)."""
    return not e <= _worst_allowed(e_c)


def _worse_reason(e: float, e_c: float) -> str:
    return (
        f"the predicted K fits worse than K_c: {e:.3f} px vs {e_c:.3f} px "
        f"(margin {100 * WORSE_RELATIVE:.0f} % + {WORSE_ABSOLUTE_PX} px)"
    )


def _implausible_reason(delta_k: np.ndarray, K: np.ndarray) -> str:
    if not np.all(np.isfinite(delta_k)):
        return "the model's Delta K is not finite"
    fx, fy, cx, cy = k_params(K)
    return f"implausible K (fx={fx:.1f}, fy={fy:.1f}, cx={cx:.1f}, cy={cy:.1f} px) outside the model's K_bounds"


class Rectifier:
    """A loaded model ready to rectify frames. ``Rectifier.load()`` uses the bundled default model."""

    def __init__(self, model: OnnxModel, mode: str = "dimenet") -> None:
        if mode not in MODES:
            raise InputError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        spec = model.spec
        if mode == "map":
            spec.map_uncertainty(model.source)
        self.model, self.mode = model, mode
        self._uncertainty = spec.uncertainty
        self._n_channels = len(spec.features.channels)
        self._kc_params = k_params(spec.K_c)
        self._kc_list = self._kc_params.tolist()
        # K_bounds as bounds on Delta K (px): a NaN fails them too.
        self._dk_low = spec.K_bounds[:, 0] - self._kc_params
        self._dk_high = spec.K_bounds[:, 1] - self._kc_params
        self._dk_bounds = tuple(zip(self._dk_low.tolist(), self._dk_high.tolist()))
        width, height = spec.image_size
        # Pixel centres run from 0 to size - 1, so the image covers [-0.5, size - 0.5] px.
        self._image_low = np.array([-0.5, -0.5])
        self._image_high = np.array([width - 0.5, height - 0.5])
        self._image_bounds = (tuple(self._image_low.tolist()), tuple(self._image_high.tolist()))
        self._K_c = np.ascontiguousarray(spec.K_c, dtype=np.float64)

    @classmethod
    def load(
        cls,
        path: Optional[str | Path] = None,
        *,
        threads: int = 1,
        providers: Optional[Sequence[str]] = None,
        mode: str = "dimenet",
    ) -> Rectifier:
        """From a ``dimenet-model/1`` .onnx file; without a path, the bundled default model.
        ``mode``: "dimenet" (the paper's method) or "map" (the network's K as a prior, fused
        with the frame's own points)."""
        if path is not None:
            return cls(load_onnx_model(path, threads=threads, providers=providers), mode)
        resource = asset(DEFAULT_MODEL)
        if not resource.is_file():
            raise ModelError(
                f"this installation has no bundled default model (dimenet/runtime/assets/{DEFAULT_MODEL}); "
                f"pass a model file from `dimenet export`"
            )
        return cls(
            onnx_model_from_bytes(
                resource.read_bytes(), f"bundled default model ({DEFAULT_MODEL})", threads=threads, providers=providers
            ),
            mode,
        )

    @property
    def spec(self) -> ModelSpec:
        return self.model.spec

    def _frame_covariance(self, feats: np.ndarray, n_points: int, pmd_error: float, invariants_3d: tuple) -> np.ndarray:
        """The network's 4x4 covariance (px^2) of one frame from its (1, D) feature, point count,
        mean PMD (px) and the ``covariance_invariants`` of its 3D points."""
        return self._uncertainty.frame_covariance(
            n_points, occupied_cells(feats, self._n_channels)[0], pmd_error, thickness(*invariants_3d)
        )

    def _plausible(self, delta_k: np.ndarray) -> np.ndarray:
        """(..., 4) px -> (...,) bool: K = K_c + Delta K is finite and inside K_bounds."""
        return np.all((delta_k >= self._dk_low) & (delta_k <= self._dk_high), -1)

    def _all_inside(self, points_2d: np.ndarray, points_3d: np.ndarray) -> bool:
        """Every point finite and inside the model's image (as ``_inside(...).all()``): (N, 2),
        (N, 3) float64 C-contiguous, or any leading dims. OpenCV's checks first (exact for all
        but the float extremes: checkRange refuses +DBL_MAX), numpy's when they say no."""
        if (
            cv2.checkRange(points_3d)[0]
            and cv2.countNonZero(cv2.inRange(points_2d.reshape(-1, 1, 2), *self._image_bounds)) == points_2d.size // 2
        ):
            return True
        return bool(self._inside(points_2d, points_3d).all())

    def _inside(self, points_2d: np.ndarray, points_3d: np.ndarray) -> np.ndarray:
        """(..., N) bool: finite 3D point and 2D point inside the model's image."""
        return np.all((points_2d >= self._image_low) & (points_2d <= self._image_high), -1) & np.isfinite(
            points_3d
        ).all(-1)

    def _raise_bad_values(self, points_2d, points_3d, valid, where: str) -> None:
        """InputError naming the first non-finite or outside-the-image point of one frame among
        its ``valid`` ones ((N,) bool, or True for all)."""
        for name, a in (("points_2d", points_2d), ("points_3d", points_3d)):
            bad = valid & ~np.isfinite(a).all(-1)
            if bad.any():
                i = int(np.argmax(bad))
                raise InputError(f"{where}{name}: point {i} is not finite ({a[i].tolist()})")
        i = int(np.argmax(valid & ~self._inside(points_2d, points_3d)))
        width, height = self.spec.image_size
        raise InputError(
            f"{where}points_2d: point {i} at ({points_2d[i, 0]:.1f}, {points_2d[i, 1]:.1f}) px is "
            f"outside the {width}x{height} px image the model was trained for"
        )

    def _validated(self, points_2d, points_3d) -> tuple[np.ndarray, np.ndarray, tuple]:
        """One frame's points as float64 (N, 2) px and (N, 3) mm with the ``covariance_invariants``
        of the 3D points, or InputError naming the problem."""
        p2 = _real_array(points_2d, "points_2d", "(N, 2)", 2, 2)
        p3 = _real_array(points_3d, "points_3d", "(N, 3)", 2, 3)
        n = len(p2)
        if len(p3) != n:
            raise InputError(f"points_2d has {n} points and points_3d {len(p3)}: they must correspond one to one")
        if n < MIN_POINTS:
            raise InputError(f"{n} points: rectification needs at least {MIN_POINTS}")
        if not self._all_inside(p2, p3):
            self._raise_bad_values(p2, p3, True, "")
        return p2, p3, _check_spread(p2, p3)

    def rectify(self, points_2d, points_3d, *, refine: bool = False) -> Rectification:
        """K and pose of one frame from its correspondences: points_2d (N, 2) px, points_3d (N, 3) mm in {W}.

        Lists and other real dtypes are accepted and cast to float64. Raises InputError for
        unusable input. See the module docstring for the pipeline and the fallback rules.
        """
        clock = time.perf_counter_ns
        t0 = clock()
        p2, p3, invariants_3d = self._validated(points_2d, points_3d)
        t1 = clock()
        spec, K_c = self.model.spec, self._K_c
        rvec_c, tvec_c = _sqpnp(p2, p3, K_c)
        t2 = clock()
        feats, points = grid_features(
            p2[None],
            p3[None],
            None,
            K_c,
            spec.image_size,
            spec.features,
            poses=(rvec_c[None], tvec_c[None]),
            return_points=True,
        )
        t3 = clock()
        dk = self.model.frame_delta_k(feats)
        t4 = clock()
        timings = {
            "validate": (t1 - t0) / 1e3,
            "pnp_kc": (t2 - t1) / 1e3,
            "features": (t3 - t2) / 1e3,
            "model": (t4 - t3) / 1e3,
        }  # microseconds
        dk_list = dk.tolist()
        K = frame_k_matrix([c + d for c, d in zip(self._kc_list, dk_list)])
        plausible = all(low <= d <= high for d, (low, high) in zip(dk_list, self._dk_bounds))
        reason = None if plausible else _implausible_reason(dk, K)
        pmd_error = _mean_norm(points[0, :2])  # the feature's PMD: the residuals under K_c at the C0 pose
        covariance = e = None
        if reason is None and self._uncertainty is not None:
            covariance = partial(self._frame_covariance, feats, len(p2), pmd_error, invariants_3d)
        rvec, tvec, dimenet_kept = rvec_c, tvec_c, False  # dimenet_kept: map failed, DIME-Net's K stands
        if reason is None and self.mode == "map":
            # From the C0 pose: MAP needs no PnP under the network's K, unless it fails.
            fit, why = map_rectify(
                p2,
                p3,
                self._kc_params + dk,
                covariance(),
                spec.K_bounds,
                K_c,
                pose=(rvec_c, tvec_c),
                uncertainty=self._uncertainty,
            )
            if why is None:
                K, dk, rvec, tvec = frame_k_matrix(fit.k.tolist()), fit.k - self._kc_params, fit.rvec, fit.tvec
                covariance, e = partial(np.array, fit.k_cov), _mean_norm(fit.residuals.T)
            else:
                reason, dimenet_kept = f"map: {why}; DIME-Net's K is returned", True
            t5 = clock()
            timings["map"], t4 = (t5 - t4) / 1e3, t5
        if (reason is None and e is None) or dimenet_kept:
            try:
                rvec, tvec = _sqpnp(p2, p3, K)
            except InputError:
                reason, dimenet_kept = "no pose under the predicted K", False
            t5 = clock()
            timings["pnp_k"], t4 = (t5 - t4) / 1e3, t5
        if refine:
            rvec_c, tvec_c = _refine(p2, p3, K_c, rvec_c, tvec_c)
            if reason is None and e is None:
                rvec, tvec = _refine(p2, p3, K, rvec, tvec)
            t5 = clock()
            timings["refine"], t4 = (t5 - t4) / 1e3, t5
            e_c = _mean_error(p2, p3, K_c, rvec_c, tvec_c)
        else:
            e_c = pmd_error
        if reason is None or dimenet_kept:
            e = _mean_error(p2, p3, K, rvec, tvec) if e is None else e
            if _worse_one(e, e_c):
                reason = _worse_reason(e, e_c)
                dimenet_kept = False
        if reason is not None and not dimenet_kept:
            K, dk, rvec, tvec, e, covariance = spec.K_c.copy(), np.zeros(4), rvec_c, tvec_c, e_c, None
        timings["check"] = (clock() - t4) / 1e3
        return Rectification(
            K=K,
            rvec=rvec,
            tvec=tvec,
            reprojection_error_px=e,
            reprojection_error_kc_px=e_c,
            delta_k=dk,
            fallback=reason,
            timings_us=timings,
            covariance=covariance,
        )

    def _validated_batch(self, points_2d, points_3d, valid, infer_mask):
        """Float64 arrays and bool masks of B frames, each frame's valid points ((N_b, 2), (N_b, 3))
        and the ``covariance_invariants_batch`` of the valid 3D points."""
        p2 = _real_array(points_2d, "points_2d", "(B, P, 2)", 3, 2)
        p3 = _real_array(points_3d, "points_3d", "(B, P, 3)", 3, 3)
        if p3.shape[:2] != p2.shape[:2]:
            raise InputError(f"points_2d has shape {p2.shape} and points_3d {p3.shape}: (B, P) must agree")
        valid = _bool_mask(valid, "valid", p2.shape[:2])
        infer = valid if infer_mask is None else _bool_mask(infer_mask, "infer_mask", p2.shape[:2])
        if np.any(infer & ~valid):
            raise InputError("infer_mask: must be a subset of valid")
        counts = valid.sum(1)
        if np.any(counts < MIN_POINTS):
            b = int(np.argmin(counts))
            raise InputError(f"frame {b}: {int(counts[b])} valid points, rectification needs at least {MIN_POINTS}")
        every = bool(valid.all())
        mask = None if every else valid
        inside = (
            self._all_inside(p2, p3)
            if every
            else self._all_inside(np.where(valid[..., None], p2, 0.0), np.where(valid[..., None], p3, 0.0))
        )
        if not inside:
            for b in np.flatnonzero(np.any(valid & ~self._inside(p2, p3), 1)):
                self._raise_bad_values(p2[b], p3[b], valid[b], f"frame {b}: ")
        frames = [(p2[b], p3[b]) if every else (p2[b][valid[b]], p3[b][valid[b]]) for b in range(len(p2))]
        spread_3d, invariants_3d = _spread_frames(p3, mask)
        spread = spread_3d & _spread_frames(p2, mask)[0]
        for b in np.flatnonzero(~spread):
            try:
                _check_spread(*frames[b])
            except InputError as exc:
                raise InputError(f"frame {b}: {exc}") from None
        return p2, p3, valid, infer, frames, invariants_3d

    def _inference_poses(self, p2, p3, infer, rvec_c, tvec_c, reasons):
        """SQPnP poses under K_c from each frame's inference points; frames with too few of
        them or no pose get a fallback reason and an empty inference mask."""
        rvec, tvec, infer = rvec_c.copy(), tvec_c.copy(), infer.copy()
        for b in range(len(p2)):
            n = int(infer[b].sum())
            try:
                if n < MIN_POINTS:
                    raise InputError(f"{n} inference points, fewer than {MIN_POINTS}")
                rvec[b], tvec[b] = _sqpnp(p2[b][infer[b]], p3[b][infer[b]], self.spec.K_c)
            except InputError as exc:
                reasons[b], infer[b] = f"no K inferred: {exc}", False
        return rvec, tvec, infer

    def rectify_batch(
        self, points_2d, points_3d, valid, *, infer_mask=None, refine: bool = False
    ) -> BatchRectification:
        """K and pose of B frames: points_2d (B, P, 2) px, points_3d (B, P, 3) mm, valid (B, P) bool.

        Features of all frames are computed together and the model runs once. Poses and
        errors use each frame's valid points; K is inferred from ``infer_mask`` (B, P), a
        subset of valid (default: valid). A frame with fewer than 6 inference points, or no
        pose from them, falls back to K_c. Same results as ``rectify`` frame by frame when
        infer_mask is valid. Raises InputError naming the first unusable frame.
        """
        p2, p3, valid, infer, frames, invariants_3d = self._validated_batch(points_2d, points_3d, valid, infer_mask)
        spec, K_c, B = self.model.spec, self._K_c, len(frames)
        rvec_c, tvec_c = np.empty((B, 3)), np.empty((B, 3))
        for b, (x, X) in enumerate(frames):
            try:
                rvec_c[b], tvec_c[b] = _sqpnp(x, X, K_c)
            except InputError as exc:
                raise InputError(f"frame {b}: {exc}") from None
        reasons: list = [None] * B
        same_poses = infer is valid
        if same_poses:
            rvec_i, tvec_i = rvec_c, tvec_c
        else:
            rvec_i, tvec_i, infer = self._inference_poses(p2, p3, infer, rvec_c, tvec_c, reasons)
        feats, points = grid_features(
            p2, p3, infer, K_c, spec.image_size, spec.features, poses=(rvec_i, tvec_i), return_points=True
        )
        dk = np.asarray(self.model.delta_k(feats.astype(np.float32)), dtype=np.float64)
        K = k_matrix(self._kc_params + dk)
        plausible = self._plausible(dk)
        rvec, tvec = rvec_c.copy(), tvec_c.copy()
        for b, (x, X) in enumerate(frames):
            if reasons[b] is None and not plausible[b]:
                reasons[b] = _implausible_reason(dk[b], K[b])
            if reasons[b] is None:
                try:
                    rvec[b], tvec[b] = _sqpnp(x, X, K[b])
                except InputError:
                    reasons[b] = "no pose under the predicted K"
        pending = np.array([r is None for r in reasons])
        mask = None if valid.all() else valid
        # With K inferred from the valid points, the feature's PMD rows are their residuals under K_c
        # at the C0 pose: their mean norm is e_c, and the uncertainty's PMD statistic.
        pmd_norms = mean_residual_norms(points[:, :2], mask) if same_poses else None
        K_cov = None
        if self._uncertainty is not None:
            K_cov = np.full((B, 4, 4), np.nan)
            if pending.any():
                if same_poses:  # validation's 3D invariants are those of the inference points
                    norms, inv = pmd_norms[pending], tuple(a[pending] for a in invariants_3d)
                else:
                    norms = mean_residual_norms(points[pending, :2], infer[pending])
                    inv = covariance_invariants_batch(p3[pending], infer[pending])
                stats = input_statistics(feats[pending], infer[pending].sum(1), norms, inv, self._n_channels)
                K_cov[pending] = self._uncertainty.covariance(stats)
        if self.mode == "map":
            self._map_batch(
                p2, p3, infer, frames, same_poses, (rvec_i, tvec_i), pending, dk, K, K_cov, rvec, tvec, reasons
            )
        if refine:
            for b, (x, X) in enumerate(frames):
                rvec_c[b], tvec_c[b] = _refine(x, X, K_c, rvec_c[b], tvec_c[b])
                if pending[b]:
                    rvec[b], tvec[b] = _refine(x, X, K[b], rvec[b], tvec[b])
        K[~pending], rvec[~pending], tvec[~pending] = K_c, rvec_c[~pending], tvec_c[~pending]
        if same_poses and not refine:
            e_c = pmd_norms  # the C0 pose and K_c on all valid points
        else:
            e_c = mean_reprojection_errors(p2, p3, mask, K_c, rotation_matrices(rvec_c), tvec_c)
        e = e_c.copy()
        if pending.any():
            e[pending] = mean_reprojection_errors(
                p2[pending],
                p3[pending],
                None if mask is None else mask[pending],
                K[pending],
                rotation_matrices(rvec[pending]),
                tvec[pending],
            )
        for b in np.flatnonzero(pending & _worse(e, e_c)):
            reasons[b] = _worse_reason(e[b], e_c[b])
        fell_back = np.array([r is not None and not r.startswith("map:") for r in reasons])
        K[fell_back], dk[fell_back] = K_c, 0.0
        rvec[fell_back], tvec[fell_back], e[fell_back] = rvec_c[fell_back], tvec_c[fell_back], e_c[fell_back]
        if K_cov is not None:
            K_cov[fell_back] = np.nan
        return BatchRectification(
            K=K,
            rvec=rvec,
            tvec=tvec,
            reprojection_error_px=e,
            reprojection_error_kc_px=e_c,
            delta_k=dk,
            fallback=tuple(reasons),
            K_cov=K_cov,
        )

    def _map_batch(
        self, p2, p3, infer, frames, same_poses, poses_c0, pending, dk, K, K_cov, rvec, tvec, reasons
    ) -> None:
        """Mode map of ``rectify_batch``, in place: each pending frame's MAP K (from its inference
        points and their C0 pose ``poses_c0``) and its pose on its valid points; a frame whose MAP
        fails keeps DIME-Net's K with a "map: ..." reason (still pending: the K_c check follows)."""
        for b in np.flatnonzero(pending):
            m = infer[b]
            fit, why = map_rectify(
                p2[b][m],
                p3[b][m],
                self._kc_params + dk[b],
                K_cov[b],
                self.spec.K_bounds,
                self._K_c,
                pose=(poses_c0[0][b], poses_c0[1][b]),
                uncertainty=self._uncertainty,
            )
            if why is not None:
                reasons[b] = f"map: {why}; DIME-Net's K is returned"
                continue
            K[b], dk[b], K_cov[b] = k_matrix(fit.k), fit.k - self._kc_params, fit.k_cov
            rvec[b], tvec[b] = (fit.rvec, fit.tvec) if same_poses else _sqpnp(*frames[b], K[b])
