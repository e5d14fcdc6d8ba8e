"""Evaluation of K estimates on a dataset: e_c, e, e* per frame and rho per scene.

Protocol (paper Sec. V-C, Tables 4 and 5): every error is measured on all the frame's
valid points; a method's K is inferred from the ``infer_mask`` points only. K_c is the
prior (from the train frames' calibration, or the model's own K_c).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable, Optional

import numpy as np

from .calibration import oracle_fit
from .dataset import Dataset
from .errors import DatasetError
from .metrics import reduction_ratio, reprojection_error_under_k

# A K predictor: a dataset (the evaluated frames) -> K (F, 3, 3) px, one per frame.
KPredictor = Callable[[Dataset], np.ndarray]


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


@dataclass(frozen=True)
class Evaluation:
    split: str
    K_c: np.ndarray
    scenes: dict  # scene name -> SceneSummary
    overall: SceneSummary
    frames: FrameErrors

    def to_json(self) -> dict:
        return {
            "split": self.split,
            "K_c": self.K_c.tolist(),
            "scenes": {name: asdict(s) for name, s in self.scenes.items()},
            "overall": asdict(self.overall),
        }


def _summary(mask: np.ndarray, errors: FrameErrors) -> SceneSummary:
    avg_e_c = float(errors.e_c[mask].mean())
    avg_e_star = float(errors.e_star[mask].mean())
    avg_e = None if errors.e is None else float(errors.e[mask].mean())
    rho = None if avg_e is None else reduction_ratio(avg_e_c, avg_e, avg_e_star)
    return SceneSummary(int(mask.sum()), avg_e_c, avg_e_star, avg_e, rho)


def frame_errors(frames: Dataset, K_c: np.ndarray, K_pred: Optional[np.ndarray] = None) -> FrameErrors:
    """e_c, e* and (with K_pred (F, 3, 3)) e of every frame, on all valid points."""
    e_c = reprojection_error_under_k(frames.points_2d, frames.points_3d, frames.valid, K_c)
    e_star = oracle_fit(frames.points_2d, frames.points_3d, frames.valid)[3]
    e = None if K_pred is None else reprojection_error_under_k(frames.points_2d, frames.points_3d, frames.valid, K_pred)
    return FrameErrors(scene=frames.scene, e_c=e_c, e_star=e_star, e=e)


def evaluate(frames: Dataset, K_c: np.ndarray, predictor: Optional[KPredictor] = None, *, split: str = "test") -> Evaluation:
    """Evaluate the given frames (already restricted to a split and any test condition)."""
    if frames.n_frames == 0:
        raise DatasetError(f"split: no {split!r} frames to evaluate")
    K_pred = None if predictor is None else np.asarray(predictor(frames), dtype=np.float64)
    errors = frame_errors(frames, K_c, K_pred)
    scenes = {name: _summary(frames.scene == name, errors) for name in sorted(set(frames.scene.tolist()))}
    overall = _summary(np.ones(frames.n_frames, bool), errors)
    return Evaluation(split=split, K_c=np.asarray(K_c), scenes=scenes, overall=overall, frames=errors)


def format_table(ev: Evaluation) -> str:
    """A small aligned table of the evaluation (px)."""
    fmt = lambda v, spec: "-" if v is None else format(v, spec)  # noqa: E731
    rows = [("scene", "frames", "Avg(e_c)", "Avg(e)", "Avg(e*)", "rho")]
    for name, s in list(ev.scenes.items()) + [("overall", ev.overall)]:
        rho = None if s.rho is None else 100 * s.rho
        rows.append((name, str(s.n_frames), fmt(s.avg_e_c, ".3f"), fmt(s.avg_e, ".3f"), fmt(s.avg_e_star, ".3f"),
                     "-" if rho is None else f"{rho:.1f}%"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in rows]
    return f"split {ev.split}, errors in px, K_c fx={ev.K_c[0,0]:.2f} fy={ev.K_c[1,1]:.2f} cx={ev.K_c[0,2]:.2f} cy={ev.K_c[1,2]:.2f}\n" + "\n".join(lines)
