"""Evaluation of K estimates on a dataset: e_c, e, e* per frame and rho per scene.

Protocol (paper Sec. V-C, Tables 4 and 5): every error is measured on all the frame's
valid points; a method's K is inferred from the ``infer_mask`` points only. K_c is the
prior (from the train frames' calibration, or the model's own K_c).

Methods compared side by side (``ALL_METHODS``; ``METHODS``: those every dataset supports):
``kc`` K_c itself; ``platform`` the K the phone's SDK reported per frame (dataset key
``K_platform``); ``self`` per-frame joint K + pose on the inference points
(``evaluation.self_calibration``); ``dimenet`` the network; ``map`` the network's prior fused
with the frame's points (``rectify.map_fit``); ``map+platform`` the same from the product of the
network's Gaussian and the platform's (K_platform with its stated 1 sigma, meta
``platform_k.sigma_px``); ``oracle`` K*; ``prior-oracle`` the per-frame MAP fit under the true population
prior of K with the true label noise (``evaluation.prior_oracle``: what one frame allows; its rows come with
each method's rho over its own, a 90 % bootstrap interval each, ``ratios``); and the product as `dimenet rectify`
runs it (``RUNTIME_METHODS``: ``rectify``, ``rectify-map``), every runtime fallback rule applied. A
dataset with lens distortion is evaluated on its undistorted points (``Dataset.undistorted``, as
``dimenet evaluate`` does). For methods with a covariance (dimenet: the network's; map: the
posterior; platform: its stated sigma), the 1-sigma coverage is the share of frames with |K -
K*| <= sigma, per parameter; on datasets that carry the true K (``K_true``, simulated ones),
also with |K - K_true| <= sigma. The two differ where K* shares the frame's noise with the
estimate: with every valid point inferring K (rig frames), a data-dominated posterior and K* err
together, so |K - K*| understates the error that the posterior describes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Optional, Union

import numpy as np

from dimenet.runtime.errors import DatasetError, ModelError
from dimenet.runtime.evaluation.calibration import oracle_fit
from dimenet.runtime.evaluation.metrics import (
    average_noise,
    ratio_interval,
    reduction_ratio,
    reprojection_error_and_variance,
    reprojection_error_under_k,
)
from dimenet.runtime.evaluation.predictor import KPrediction, Predictor
from dimenet.runtime.evaluation.prior_oracle import PRIOR_ORACLE, missing_inputs, prior_oracle
from dimenet.runtime.evaluation.self_calibration import self_calibrate
from dimenet.runtime.evaluation.uncertainty_fit import coverage
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import homography_floor, k_matrix, k_params
from dimenet.runtime.rectify.map_fit import map_rectify
from dimenet.runtime.rectify.rectifier import Rectifier

# A K predictor: a dataset (the evaluated frames) -> K (F, 3, 3) px, one per frame.
KPredictor = Callable[[Dataset], np.ndarray]
METHODS = ("kc", "self", "dimenet", "map", "oracle")  # the methods of every dataset (reproduce's tables)
PLATFORM_METHODS = ("platform", "map+platform")  # those that need the dataset's K_platform
ALL_METHODS = ("kc", "platform", "self", "dimenet", "map", "map+platform", "oracle", PRIOR_ORACLE)
NATURAL = "natural"  # the scene whose modes the prior oracle goes beside (``with_prior_oracle``)
# The product's rectifier (``Rectifier.rectify_batch``, modes dimenet and map) with every fallback
# rule of the runtime, where dimenet and map are the paper's protocol (the network's K on every
# frame, the K-bounds rule only): training/METHOD.md, "Metric and protocol".
RUNTIME_METHODS = ("rectify", "rectify-map")
MODEL_METHODS = ("dimenet", "map", "map+platform", *RUNTIME_METHODS)


# The reference of frames whose K is not observable (one view of one plane), and the suffix of
# their scene's name: their rho is against the homography floor, not e*.
FLOOR = "homography floor"
ONE_PLANE = " (one plane)"


@dataclass(frozen=True)
class SceneSummary:
    """Averages (px) over the frames of one scene; avg_e and rho are None without a model, rho
    also when its denominator is within the errors' noise (``metrics.reduction_ratio``);
    avg_e_star is the reference's: e* ("K*"), or the homography floor of frames of one plane
    (FLOOR)."""

    n_frames: int
    avg_e_c: float
    avg_e_star: float
    avg_e: Optional[float]
    rho: Optional[float]
    reference: str = "K*"


@dataclass(frozen=True)
class FrameErrors:
    """Per-frame errors (px) of the evaluated frames; e is None without a model; e_star is the
    homography floor where ``floor`` (F,) bool (the frame's K is not observable, K* NaN);
    e_c_var (F,) px^2 the variance of each e_c (``metrics.reprojection_error_and_variance``)."""

    scene: np.ndarray
    e_c: np.ndarray
    e_star: np.ndarray
    e: Optional[np.ndarray]
    K_star: np.ndarray  # (F, 3, 3) px
    floor: Optional[np.ndarray] = None
    e_c_var: Optional[np.ndarray] = None


@dataclass(frozen=True)
class MethodEstimate:
    """One method's K (F, 3, 3) px per frame; K_cov (F, 4, 4) px^2 of (fx, fy, cx, cy) or None;
    fallbacks: how many frames the method could not estimate (they get K_c, or for map the
    DIME-Net K)."""

    K: np.ndarray
    K_cov: Optional[np.ndarray]
    fallbacks: int


@dataclass(frozen=True)
class Evaluation:
    split: str
    K_c: np.ndarray
    scenes: dict  # scene name -> SceneSummary
    overall: SceneSummary
    frames: FrameErrors
    methods: dict = field(default_factory=dict)  # method -> scene name -> SceneSummary
    coverage: dict = field(default_factory=dict)  # method -> parameter -> share of frames within 1 sigma of K*
    coverage_true: dict = field(default_factory=dict)  # the same against K_true, when the dataset has it
    fallbacks: dict = field(default_factory=dict)  # method -> frames it could not estimate
    # Frames that give no K* (a planar view), measured against their homography floor: reason -> count.
    floor_reasons: dict = field(default_factory=dict)
    # With the prior oracle among the methods: method -> scene name -> metrics.RatioInterval of its rho over the
    # prior oracle's.
    ratios: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        d = {
            "split": self.split,
            "K_c": self.K_c.tolist(),
            "scenes": {name: asdict(s) for name, s in self.scenes.items()},
            "overall": asdict(self.overall),
        }
        if self.floor_reasons:
            d["against_floor"] = self.floor_reasons
        if self.methods:
            d["methods"] = {m: {name: asdict(s) for name, s in scenes.items()} for m, scenes in self.methods.items()}
            d["coverage"] = self.coverage
            if self.coverage_true:
                d["coverage_true"] = self.coverage_true
            d["fallbacks"] = self.fallbacks
        if self.ratios:
            d["ratios_to_prior_oracle"] = {
                m: {name: asdict(r) for name, r in scenes.items()} for m, scenes in self.ratios.items()
            }
        return d


def _summary(mask: np.ndarray, errors: FrameErrors) -> SceneSummary:
    avg_e_c = float(errors.e_c[mask].mean())
    avg_e_star = float(errors.e_star[mask].mean())
    avg_e = None if errors.e is None else float(errors.e[mask].mean())
    noise = 0.0 if errors.e_c_var is None else average_noise(errors.e_c_var[mask])
    rho = None if avg_e is None else reduction_ratio(avg_e_c, avg_e, avg_e_star, noise)
    floor = errors.floor is not None and bool(errors.floor[mask].all())
    return SceneSummary(int(mask.sum()), avg_e_c, avg_e_star, avg_e, rho, FLOOR if floor else "K*")


def frame_errors(
    frames: Dataset, K_c: np.ndarray, K_pred: Optional[np.ndarray] = None, oracle: Optional[tuple] = None
) -> FrameErrors:
    """e_c, e*, K* and (with K_pred (F, 3, 3)) e of every frame, on all valid points; ``oracle``:
    the frames' (K*, e*, reasons) when already fitted. A frame without K* (its reason says why: one
    plane) has the homography floor as its e* (``floor``)."""
    e_c, e_c_var = reprojection_error_and_variance(frames.points_2d, frames.points_3d, frames.valid, K_c)
    if oracle is None:
        K_star, _, _, e_star, reasons = oracle_fit(frames.points_2d, frames.points_3d, frames.valid)
    else:
        K_star, e_star, reasons = oracle
    floor = np.array([r is not None for r in reasons], bool)
    if floor.any():
        e_star = e_star.copy()
        e_star[floor] = homography_floor(frames.points_2d[floor], frames.points_3d[floor], frames.valid[floor])
    e = None if K_pred is None else reprojection_error_under_k(frames.points_2d, frames.points_3d, frames.valid, K_pred)
    return FrameErrors(scene=frames.scene, e_c=e_c, e_star=e_star, e=e, K_star=K_star, floor=floor, e_c_var=e_c_var)


def require_platform(frames: Dataset, methods: Sequence[str]) -> None:
    """DatasetError (one line) when a method of ``methods`` needs K_platform and ``frames`` have
    none, or (map+platform) K_platform's stated 1 sigma and the dataset states none."""
    wanting = [m for m in methods if m in PLATFORM_METHODS]
    if wanting and frames.K_platform is None:
        raise DatasetError(
            f"methods: {wanting[0]!r} needs K_platform (the phone SDK's K per frame) and this dataset has none "
            "(`dimenet simulate --platform-k` simulates one)"
        )
    if "map+platform" in methods and platform_sigma_px(frames) is None:
        raise DatasetError("methods: 'map+platform' needs K_platform's stated 1 sigma (meta platform_k.sigma_px)")


def platform_sigma_px(frames: Dataset) -> Optional[np.ndarray]:
    """(4,) px the stated 1 sigma of K_platform's (fx, fy, cx, cy) (meta ``platform_k.sigma_px``),
    None when the dataset states none; DatasetError when it is not 4 positive finite numbers."""
    stated = frames.meta.get("platform_k")
    if not isinstance(stated, dict) or "sigma_px" not in stated:
        return None
    try:
        sigma = np.asarray(stated["sigma_px"], dtype=np.float64)
    except (TypeError, ValueError):
        sigma = np.full(0, np.nan)
    if sigma.shape != (4,) or not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise DatasetError(f"meta: platform_k.sigma_px must be 4 positive px (fx, fy, cx, cy): {stated['sigma_px']!r}")
    return sigma


def fused_prior(k_a: np.ndarray, cov_a: np.ndarray, k_b: np.ndarray, cov_b: np.ndarray) -> tuple:
    """The product of two Gaussians over k (4,) px, covariances (4, 4) px^2 -> (k, cov)."""
    info_a, info_b = np.linalg.inv(cov_a), np.linalg.inv(cov_b)
    cov = np.linalg.inv(info_a + info_b)
    return cov @ (info_a @ k_a + info_b @ k_b), cov


def platform_prior(frames: Dataset, prediction: KPrediction) -> KPrediction:
    """The network's prediction fused with the platform's (K_platform, its stated sigma) per
    frame; frames the network does not predict get the platform's alone (all count as predicted).
    The frames have passed ``require_platform``."""
    cov_p = np.diag(platform_sigma_px(frames) ** 2)
    K, K_cov = frames.K_platform.copy(), np.broadcast_to(cov_p, (frames.n_frames, 4, 4)).copy()
    for f in np.flatnonzero(prediction.predicted):
        k, K_cov[f] = fused_prior(k_params(prediction.K[f]), prediction.K_cov[f], k_params(K[f]), cov_p)
        K[f] = k_matrix(k)
    return replace(prediction, K=K, K_cov=K_cov, predicted=np.ones(frames.n_frames, bool))


def map_estimate(
    frames: Dataset, predictor: Predictor, prediction: KPrediction, *, with_platform: bool = False
) -> MethodEstimate:
    """The map method: per frame, ``map_rectify`` on its inference points from the network's
    K and covariance (``prediction``, the predictor's on these frames), or with
    ``with_platform`` from their product with the platform's (``platform_prior``); frames
    without a prior keep K_c, failed fits the prior's K."""
    uncertainty = predictor.spec.map_uncertainty(predictor.source)
    if with_platform:
        prediction = platform_prior(frames, prediction)
    K, K_cov = prediction.K.copy(), prediction.K_cov.copy()
    fallbacks = int((~prediction.predicted).sum())
    for f in np.flatnonzero(prediction.predicted):
        m = frames.infer_mask[f]
        fit, reason = map_rectify(
            frames.points_2d[f][m],
            frames.points_3d[f][m],
            k_params(K[f]),
            K_cov[f],
            predictor.K_bounds,
            predictor.K_c,
            uncertainty=uncertainty,
        )
        if reason is None:
            K[f], K_cov[f] = k_matrix(fit.k), fit.K_cov
        else:
            fallbacks += 1
    return MethodEstimate(K=K, K_cov=K_cov, fallbacks=fallbacks)


def runtime_estimate(frames: Dataset, predictor: Predictor, mode: str) -> MethodEstimate:
    """The rectifier's K per frame in ``mode`` from the inference points alone, every fallback rule applied (a frame
    that keeps K_c counts as a fallback; map's soft fallbacks to DIME-Net's K do not), as `dimenet rectify` returns
    it for an app that has only those points: the rules read no point the frame is scored on beyond them (a
    natural frame's board)."""
    rect = Rectifier(predictor, mode, predictor.camera)
    infer = frames.infer_mask
    r = rect.rectify_batch(frames.points_2d, frames.points_3d, infer, infer_mask=infer)
    kept = sum(f is not None and f.refusal for f in r.fallback)
    return MethodEstimate(K=r.K, K_cov=r.K_cov, fallbacks=kept)


def method_estimate(
    method: str,
    frames: Dataset,
    K_c: np.ndarray,
    K_star: np.ndarray,
    predictor: Optional[Predictor],
    prediction: Optional[KPrediction],
) -> MethodEstimate:
    """K per frame of one of ALL_METHODS on the given frames (K* (F, 3, 3) from ``frame_errors``;
    ``prediction`` the predictor's on these frames)."""
    if method not in ALL_METHODS + RUNTIME_METHODS:
        known = ", ".join(ALL_METHODS + RUNTIME_METHODS)
        raise DatasetError(f"methods: unknown method {method!r} (known: {known})")
    if method in MODEL_METHODS and predictor is None:
        raise ModelError(f"methods: {method!r} needs a model (--model)")
    require_platform(frames, (method,))
    if method == "kc":
        return MethodEstimate(K=np.broadcast_to(K_c, K_star.shape).copy(), K_cov=None, fallbacks=0)
    if method == "platform":
        sigma = platform_sigma_px(frames)
        K_cov = None if sigma is None else np.broadcast_to(np.diag(sigma**2), (frames.n_frames, 4, 4)).copy()
        return MethodEstimate(K=frames.K_platform, K_cov=K_cov, fallbacks=0)
    if method == "oracle":
        return MethodEstimate(K=K_star, K_cov=None, fallbacks=0)
    if method == PRIOR_ORACLE:
        po = prior_oracle(frames)
        return MethodEstimate(K=po.K, K_cov=po.K_cov, fallbacks=po.fallbacks)
    if method == "self":
        sc = self_calibrate(frames, K_c)
        return MethodEstimate(K=sc.K, K_cov=None, fallbacks=sum(r is not None for r in sc.fallback))
    if method == "dimenet":
        return MethodEstimate(K=prediction.K, K_cov=prediction.K_cov, fallbacks=int((~prediction.predicted).sum()))
    if method in RUNTIME_METHODS:
        return runtime_estimate(frames, predictor, "map" if method == "rectify-map" else "dimenet")
    if method == "map+platform":
        return map_estimate(frames, predictor, prediction, with_platform=True)
    return map_estimate(frames, predictor, prediction)


def evaluate(
    frames: Dataset,
    K_c: np.ndarray,
    predictor: Union[Predictor, KPredictor, None] = None,
    *,
    split: str = "test",
    methods: Sequence[str] = (),
) -> Evaluation:
    """Evaluate the given frames (already restricted to a split and any test condition): e with
    the predictor's K, and one row per method of ``methods`` (dimenet and map need a Predictor).
    Frames that give no K* (all points in one plane) are measured against their homography floor,
    in scenes of their own (``ONE_PLANE``), counted by reason in ``floor_reasons``; ``overall`` is
    over the frames with K*, or over all frames when none has one."""
    if frames.n_frames == 0:
        raise DatasetError(f"split: no {split!r} frames to evaluate")
    require_platform(frames, methods)
    K_star, _, _, e_star, reasons = oracle_fit(frames.points_2d, frames.points_3d, frames.valid)
    floor_reasons: dict = {}
    for r in reasons:
        if r is not None:
            floor_reasons[r] = floor_reasons.get(r, 0) + 1
    model = predictor if isinstance(predictor, Predictor) else None
    prediction = None if model is None else model.predict(frames)
    if prediction is not None:
        K_pred = prediction.K
    else:
        K_pred = None if predictor is None else np.asarray(predictor(frames), dtype=np.float64)
    errors = frame_errors(frames, K_c, K_pred, (K_star, e_star, reasons))
    groups = np.where(errors.floor, np.char.add(frames.scene.astype(str), ONE_PLANE), frames.scene.astype(str))
    names = sorted(set(groups.tolist()))
    scenes = {name: _summary(groups == name, errors) for name in names}
    # Overall: the frames with K* (the paper's rho), unless every frame is of one plane.
    whole = ~errors.floor if not errors.floor.all() else np.ones(frames.n_frames, bool)
    overall = _summary(whole, errors)
    rows, covered, covered_true, fallbacks, per_frame = {}, {}, {}, {}, {}
    for method in dict.fromkeys(methods):
        est = method_estimate(method, frames, K_c, errors.K_star, model, prediction)
        e = (
            errors.e_star
            if method == "oracle"
            else reprojection_error_under_k(frames.points_2d, frames.points_3d, frames.valid, est.K)
        )
        mine, per_frame[method] = replace(errors, e=e), e
        rows[method] = {name: _summary(groups == name, mine) for name in names}
        rows[method]["overall"] = _summary(whole, mine)
        fallbacks[method] = est.fallbacks
        if est.K_cov is not None:
            ok = np.all(np.isfinite(est.K_cov), axis=(1, 2)) & ~errors.floor
            if not ok.any():  # no frame with K* (all of one plane): no coverage to measure
                continue
            covered[method] = coverage(k_params(est.K[ok]), k_params(errors.K_star[ok]), est.K_cov[ok])
            if frames.K_true is not None:
                covered_true[method] = coverage(k_params(est.K[ok]), k_params(frames.K_true[ok]), est.K_cov[ok])
    ratios = {}
    if PRIOR_ORACLE in per_frame:
        masks = {**{name: groups == name for name in names}, "overall": whole}
        ratios = {
            m: {name: ratio_interval(errors.e_c[k], e[k], per_frame[PRIOR_ORACLE][k]) for name, k in masks.items()}
            for m, e in per_frame.items()
            if m != PRIOR_ORACLE
        }
    return Evaluation(
        split=split,
        K_c=np.asarray(K_c),
        scenes=scenes,
        overall=overall,
        frames=errors,
        methods=rows,
        coverage=covered,
        coverage_true=covered_true,
        fallbacks=fallbacks,
        floor_reasons=floor_reasons,
        ratios=ratios,
    )


def format_table(ev: Evaluation) -> str:
    """A small aligned table of the evaluation (px), then one row per method and scene."""
    fmt = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
    rho = lambda s: "-" if s.avg_e is None else "n/a" if s.rho is None else f"{100 * s.rho:.1f}%"  # noqa: E731
    rows = [("scene", "frames", "Avg(e_c)", "Avg(e)", "Avg(e*)", "rho")]
    for name, s in list(ev.scenes.items()) + [("overall", ev.overall)]:
        rows.append(
            (name, str(s.n_frames), fmt(s.avg_e_c, ".3f"), fmt(s.avg_e, ".3f"), fmt(s.avg_e_star, ".3f"), rho(s))
        )
    text = [
        f"split {ev.split}, errors in px, K_c fx={ev.K_c[0, 0]:.2f} fy={ev.K_c[1, 1]:.2f} cx={ev.K_c[0, 2]:.2f} "
        f"cy={ev.K_c[1, 2]:.2f}",
        _aligned(rows),
    ]
    for reason, n in ev.floor_reasons.items():
        text.append(
            f"{n} frame(s) without K* ({reason}): scenes marked{ONE_PLANE}, Avg(e*) is their homography floor "
            "(the best error any pinhole K reaches on one plane) and rho is against it"
        )
    if any(s.rho is None and s.avg_e is not None for s in ev.scenes.values()):
        text.append("rho n/a: Avg(e_c) - Avg(e*) is within twice the noise of Avg(e_c) (no room to improve)")
    if ev.methods:
        header = ("method", "scene", "frames", "Avg(e)", "rho", "fallbacks", "1-sigma coverage fx/fy/cx/cy vs K*")
        rows = [header + (("vs K_true",) if ev.coverage_true else ())]
        share = lambda cov: "-" if cov is None else "/".join(f"{100 * v:.0f}%" for v in cov.values())  # noqa: E731
        for method, scenes in ev.methods.items():
            covs = [share(ev.coverage.get(method))] + (
                [share(ev.coverage_true.get(method))] if ev.coverage_true else []
            )
            for name, s in scenes.items():
                rows.append(
                    (
                        method,
                        name,
                        str(s.n_frames),
                        fmt(s.avg_e, ".3f"),
                        rho(s),
                        str(ev.fallbacks[method]) if name == "overall" else "",
                        *(covs if name == "overall" else [""] * len(covs)),
                    )
                )
        text += ["", _aligned(rows)]
    if ev.ratios:
        text += ["", _ratio_table(ev.ratios)]
    return "\n".join(text)


def _ratio_table(ratios: dict) -> str:
    """rho / rho(prior-oracle) per method and scene with its interval (``metrics.ratio_interval``)."""
    level = next(iter(next(iter(ratios.values())).values())).level
    rows = [("method", "scene", "frames", f"rho / rho({PRIOR_ORACLE})", f"{100 * level:.0f}% interval")]
    for method, scenes in ratios.items():
        for name, r in scenes.items():
            ratio = "n/a" if r.ratio is None else f"{r.ratio:.3f}"
            interval = "-" if r.low is None else f"[{r.low:.3f}, {r.high:.3f}]"
            rows.append((method, name, str(r.n_frames), ratio, interval))
    note = (
        f"{PRIOR_ORACLE}: per frame, the MAP (K, pose) under the true population prior of K (its scene's K_true) "
        "with the true label noise, what one frame allows; intervals: bootstrap over the frames"
    )
    return _aligned(rows) + "\n" + note


def with_prior_oracle(frames: Dataset, methods: Sequence[str]) -> tuple[tuple, Optional[str]]:
    """``methods`` with the prior oracle added where it goes: beside the modes (MODEL_METHODS) on natural frames.
    (methods, None), or (methods unchanged, why not) when the frames lack what it needs (``prior_oracle``)."""
    methods = tuple(methods)
    wanted = PRIOR_ORACLE not in methods and any(m in MODEL_METHODS for m in methods) and NATURAL in frames.scene
    if not wanted:
        return methods, None
    why = missing_inputs(frames)
    return (methods, f"{PRIOR_ORACLE} n/a on the natural frames: {why}") if why else ((*methods, PRIOR_ORACLE), None)


def _aligned(rows: list) -> str:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join(
        "  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip() for r in rows
    )
