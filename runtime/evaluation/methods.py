"""Evaluation of K estimates on a dataset: e_c, e, e* per frame and rho per scene.

Protocol (paper Sec. V-C, Tables 4 and 5): every error is measured on all the frame's
valid points; a method's K is inferred from the ``infer_mask`` points only. K_c is the
prior (from the train frames' calibration, or the model's own K_c).

Methods compared side by side (``METHODS``): ``kc`` K_c itself; ``self`` per-frame joint
K + pose on the inference points (``evaluation.self_calibration``); ``dimenet`` the network;
``map`` the network's prior fused with the frame's points (``rectify.map_fit``); ``oracle``
K*. For methods with a covariance (dimenet: the network's; map: the posterior), the 1-sigma
coverage is the share of frames with |K - K*| <= sigma, per parameter; on datasets that carry
the true K (``K_true``, simulated ones), also with |K - K_true| <= sigma. The two differ where
K* shares the frame's noise with the estimate: with every valid point inferring K (rig
frames), a data-dominated posterior and K* err together, so |K - K*| understates the error
that the posterior describes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional, Union

import numpy as np

from dimenet.runtime.errors import DatasetError, ModelError
from dimenet.runtime.evaluation.calibration import oracle_fit
from dimenet.runtime.evaluation.metrics import reduction_ratio, reprojection_error_under_k
from dimenet.runtime.evaluation.predictor import KPrediction, Predictor
from dimenet.runtime.evaluation.self_calibration import self_calibrate
from dimenet.runtime.evaluation.uncertainty_fit import coverage
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.rectify.map_fit import map_rectify

# A K predictor: a dataset (the evaluated frames) -> K (F, 3, 3) px, one per frame.
KPredictor = Callable[[Dataset], np.ndarray]
METHODS = ("kc", "self", "dimenet", "map", "oracle")
MODEL_METHODS = ("dimenet", "map")


@dataclass(frozen=True)
class SceneSummary:
    """Averages (px) over the frames of one scene; avg_e and rho are None without a model."""

    n_frames: int
    avg_e_c: float
    avg_e_star: float
    avg_e: Optional[float]
    rho: Optional[float]


@dataclass(frozen=True)
class FrameErrors:
    """Per-frame errors (px) of the evaluated frames; e is None without a model."""

    scene: np.ndarray
    e_c: np.ndarray
    e_star: np.ndarray
    e: Optional[np.ndarray]
    K_star: np.ndarray  # (F, 3, 3) px


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

    def to_json(self) -> dict:
        d = {
            "split": self.split,
            "K_c": self.K_c.tolist(),
            "scenes": {name: asdict(s) for name, s in self.scenes.items()},
            "overall": asdict(self.overall),
        }
        if self.methods:
            d["methods"] = {m: {name: asdict(s) for name, s in scenes.items()} for m, scenes in self.methods.items()}
            d["coverage"] = self.coverage
            if self.coverage_true:
                d["coverage_true"] = self.coverage_true
            d["fallbacks"] = self.fallbacks
        return d


def _summary(mask: np.ndarray, errors: FrameErrors) -> SceneSummary:
    avg_e_c = float(errors.e_c[mask].mean())
    avg_e_star = float(errors.e_star[mask].mean())
    avg_e = None if errors.e is None else float(errors.e[mask].mean())
    rho = None if avg_e is None else reduction_ratio(avg_e_c, avg_e, avg_e_star)
    return SceneSummary(int(mask.sum()), avg_e_c, avg_e_star, avg_e, rho)


def frame_errors(frames: Dataset, K_c: np.ndarray, K_pred: Optional[np.ndarray] = None) -> FrameErrors:
    """e_c, e*, K* and (with K_pred (F, 3, 3)) e of every frame, on all valid points."""
    e_c = reprojection_error_under_k(frames.points_2d, frames.points_3d, frames.valid, K_c)
    K_star, _, _, e_star = oracle_fit(frames.points_2d, frames.points_3d, frames.valid)
    e = None if K_pred is None else reprojection_error_under_k(frames.points_2d, frames.points_3d, frames.valid, K_pred)
    return FrameErrors(scene=frames.scene, e_c=e_c, e_star=e_star, e=e, K_star=K_star)


def map_estimate(frames: Dataset, predictor: Predictor, prediction: KPrediction) -> MethodEstimate:
    """The map method: per frame, ``map_rectify`` on its inference points from the network's
    K and covariance (``prediction``, the predictor's on these frames); frames the network
    does not predict keep K_c, failed fits its K."""
    uncertainty = predictor.spec.map_uncertainty(predictor.source)
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


def method_estimate(
    method: str,
    frames: Dataset,
    K_c: np.ndarray,
    K_star: np.ndarray,
    predictor: Optional[Predictor],
    prediction: Optional[KPrediction],
) -> MethodEstimate:
    """K per frame of one of METHODS on the given frames (K* (F, 3, 3) from ``frame_errors``;
    ``prediction`` the predictor's on these frames)."""
    if method not in METHODS:
        raise DatasetError(f"methods: unknown method {method!r} (known: {', '.join(METHODS)})")
    if method in MODEL_METHODS and predictor is None:
        raise ModelError(f"methods: {method!r} needs a model (--model)")
    if method == "kc":
        return MethodEstimate(K=np.broadcast_to(K_c, K_star.shape).copy(), K_cov=None, fallbacks=0)
    if method == "oracle":
        return MethodEstimate(K=K_star, K_cov=None, fallbacks=0)
    if method == "self":
        sc = self_calibrate(frames, K_c)
        return MethodEstimate(K=sc.K, K_cov=None, fallbacks=sum(r is not None for r in sc.fallback))
    if method == "dimenet":
        return MethodEstimate(K=prediction.K, K_cov=prediction.K_cov, fallbacks=int((~prediction.predicted).sum()))
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
    the predictor's K, and one row per method of ``methods`` (dimenet and map need a Predictor)."""
    if frames.n_frames == 0:
        raise DatasetError(f"split: no {split!r} frames to evaluate")
    model = predictor if isinstance(predictor, Predictor) else None
    prediction = None if model is None else model.predict(frames)
    if prediction is not None:
        K_pred = prediction.K
    else:
        K_pred = None if predictor is None else np.asarray(predictor(frames), dtype=np.float64)
    errors = frame_errors(frames, K_c, K_pred)
    names = sorted(set(frames.scene.tolist()))
    scenes = {name: _summary(frames.scene == name, errors) for name in names}
    overall = _summary(np.ones(frames.n_frames, bool), errors)
    rows, covered, covered_true, fallbacks = {}, {}, {}, {}
    for method in dict.fromkeys(methods):
        est = method_estimate(method, frames, K_c, errors.K_star, model, prediction)
        e = (
            errors.e_star
            if method == "oracle"
            else reprojection_error_under_k(frames.points_2d, frames.points_3d, frames.valid, est.K)
        )
        mine = FrameErrors(scene=errors.scene, e_c=errors.e_c, e_star=errors.e_star, e=e, K_star=errors.K_star)
        rows[method] = {name: _summary(frames.scene == name, mine) for name in names}
        rows[method]["overall"] = _summary(np.ones(frames.n_frames, bool), mine)
        fallbacks[method] = est.fallbacks
        if est.K_cov is not None:
            ok = np.all(np.isfinite(est.K_cov), axis=(1, 2))
            covered[method] = coverage(k_params(est.K[ok]), k_params(errors.K_star[ok]), est.K_cov[ok])
            if frames.K_true is not None:
                covered_true[method] = coverage(k_params(est.K[ok]), k_params(frames.K_true[ok]), est.K_cov[ok])
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
    )


def format_table(ev: Evaluation) -> str:
    """A small aligned table of the evaluation (px), then one row per method and scene."""
    fmt = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
    pct = lambda v: "-" if v is None else f"{100 * v:.1f}%"  # noqa: E731
    rows = [("scene", "frames", "Avg(e_c)", "Avg(e)", "Avg(e*)", "rho")]
    for name, s in list(ev.scenes.items()) + [("overall", ev.overall)]:
        rows.append(
            (name, str(s.n_frames), fmt(s.avg_e_c, ".3f"), fmt(s.avg_e, ".3f"), fmt(s.avg_e_star, ".3f"), pct(s.rho))
        )
    text = [
        f"split {ev.split}, errors in px, K_c fx={ev.K_c[0, 0]:.2f} fy={ev.K_c[1, 1]:.2f} cx={ev.K_c[0, 2]:.2f} "
        f"cy={ev.K_c[1, 2]:.2f}",
        _aligned(rows),
    ]
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
                        pct(s.rho),
                        str(ev.fallbacks[method]) if name == "overall" else "",
                        *(covs if name == "overall" else [""] * len(covs)),
                    )
                )
        text += ["", _aligned(rows)]
    return "\n".join(text)


def _aligned(rows: list) -> str:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join(
        "  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip() for r in rows
    )
