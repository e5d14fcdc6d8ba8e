"""The real-photo suite: public photo sets no one on this project made, each ingested, calibrated
with and without a lens model and rectified in both modes, against the do-no-harm targets
(training/METHOD.md, "Residual structure"; models_spec/real-photos.md).

A set names its photos per camera, how its K_c is had (a published K, or ``dimenet calibrate`` on
the set) and what its truth is: ``reference="K_c"`` for a camera without OIS (every frame's
principal point is K_c's), ``"K_star"`` for views that fix K alone (each photo's own calibration).
Targets, per (set, lens, mode):

- every frame: e <= e_c, no exception;
- ``K_c``: |delta c| <= 2 sigma (per axis) on >= NO_OIS_COVERED of the frames and a median
  |delta c| <= NO_OIS_MEDIAN_PX (px);
- ``K_star``: each frame's K within 2 sigma of its K* per parameter, or K_c with a reason.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from dimenet.runtime.errors import DimenetError, IngestError
from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.rig import load_rig
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.ingest.pipeline import ingest
from dimenet.runtime.rectify.rectifier import MODES, Rectifier
from dimenet.runtime.rectify.user_camera import Camera

NO_OIS_COVERED = 0.9
NO_OIS_MEDIAN_PX = 5.0
LENS_MODEL = "opencv5"


@dataclass(frozen=True)
class SuiteSet:
    """One camera's photos in a folder of the suite's root: ``photos`` glob patterns; ``published_k``
    (fx, fy, cx, cy) px, the K_c without a lens model (None: calibrated on the set); ``reference``
    "K_c" or "K_star" (the module docstring)."""

    name: str
    folder: str
    photos: tuple
    reference: str
    published_k: Optional[tuple] = None


# The sets of ../shared/real-photos (sources, licences and layout: README.md, "Real photos"; their calibrations:
# that folder's README).
SETS = (
    SuiteSet("ortho-left", "ortho", ("left.jpg", "left_calib.jpg"), "K_star", (1649.4, 1654.1, 793.3, 614.4)),
    SuiteSet("ortho-right", "ortho", ("right.jpg", "right_calib.jpg"), "K_star", (1631.7, 1625.7, 789.1, 634.8)),
    SuiteSet("huawei-y5", "huawei-y5", ("*.jpg",), "K_c"),
)
# Beside each folder's photos, its rig (dimenet-rig/1): the bundled asset of that folder, which
# `dimenet samples` writes there (the photos are the sets' own, never the project's).
RIG_FILE = "rig.json"
RIG_ASSETS = {"ortho": "real_photos_ortho_rig.json", "huawei-y5": "real_photos_huawei_y5_rig.json"}


@dataclass(frozen=True)
class SuiteRow:
    """One (set, lens, mode): frames; Avg(e_c) and Avg(e) px; fallbacks (K_c kept) and how many of
    them by the structure rule; worse: frames with e > e_c; covered: the share of frames meeting
    the reference's 2-sigma test; median_dc_px: the median |K's c - K_c's c| (px); met: the
    targets; problem: why the row could not run (an exception: a finding), else None."""

    set_name: str
    lens: bool
    mode: str
    frames: int = 0
    avg_e_c_px: float = float("nan")
    avg_e_px: float = float("nan")
    fallbacks: int = 0
    structure: int = 0
    worse: int = 0
    covered: float = float("nan")
    median_dc_px: float = float("nan")
    met: bool = False
    problem: Optional[str] = None

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in d.items()}


def _photos(root: Path, s: SuiteSet) -> list:
    folder = root / s.folder
    return sorted({p for pattern in s.photos for p in folder.glob(pattern)})


def missing_sets(root: Path) -> list:
    """The names of the suite's sets whose photos or rig file are not under ``root``."""
    return [s.name for s in SETS if not _photos(root, s) or not (root / s.folder / RIG_FILE).is_file()]


def _stderr_line(line: str) -> None:
    print(line, file=sys.stderr)


def _ingested(root: Path, s: SuiteSet, note: Callable[[str], None]) -> Dataset:
    """The set's photos ingested, one ``note`` line for each photo ingest drops (its path and why);
    IngestError when none gave a frame."""
    photos = _photos(root, s)
    ingestion = ingest(photos, load_rig(root / s.folder / RIG_FILE), split="train")
    for path, result in zip(photos, ingestion.results):
        if result.skipped is not None:
            note(f"real-photo suite: {s.name}: dropped {path}: {result.skipped}")
    if ingestion.dataset is None:
        raise IngestError(f"none of the {len(photos)} photos of {s.name} gave a frame")
    return ingestion.dataset


def _cameras(ds: Dataset, s: SuiteSet) -> tuple:
    """(pinhole camera, its per-frame K*), (lens camera, its K*): K_c calibrated on the set (or the
    published K) without a lens, and K_c with LENS_MODEL's lens about the K the fit states it about,
    as ``dimenet calibrate --distortion`` leaves them."""
    size = tuple(int(v) for v in ds.image_size)
    pinhole = calibrate_dataset(ds)
    K_pinhole = pinhole.K_c if s.published_k is None else k_matrix(np.array(s.published_k))
    lens = calibrate_dataset(ds, LENS_MODEL)
    with_lens = Camera(lens.K_c, size, lens.dist_coeffs, lens.dist_K)
    return (Camera(K_pinhole, size), pinhole.K_star), (with_lens, lens.K_star)


def _row(s: SuiteSet, ds: Dataset, camera: Camera, K_star, model, mode: str, lens: bool) -> SuiteRow:
    rect = Rectifier(model, mode, camera)
    r = rect.rectify_batch(ds.points_2d, ds.points_3d, ds.valid)
    kept = np.array([f is not None and f.refusal for f in r.fallback])
    dc = r.K[:, :2, 2] - rect.K_c[:2, 2]
    sigma = np.sqrt(np.diagonal(r.K_cov, axis1=1, axis2=2)) if r.K_cov is not None else np.full((len(dc), 4), np.nan)
    if s.reference == "K_c":
        ok = np.all(np.abs(dc) <= 2 * sigma[:, 2:], axis=1)
        covered = float(ok.mean())
        met_reference = covered >= NO_OIS_COVERED and float(np.median(np.hypot(*dc.T))) <= NO_OIS_MEDIAN_PX
    else:
        # K_star is under the lens model where the camera has one: the K the rectifier returns is that camera's.
        gap = np.abs(k_params(r.K) - k_params(K_star))
        ok = kept | np.all(gap <= 2 * sigma, axis=1)
        covered = float(ok.mean())
        met_reference = bool(ok.all())
    worse = int(np.count_nonzero(~(r.reprojection_error_px <= r.reprojection_error_kc_px)))
    return SuiteRow(
        set_name=s.name,
        lens=lens,
        mode=mode,
        frames=len(dc),
        avg_e_c_px=float(np.mean(r.reprojection_error_kc_px)),
        avg_e_px=float(np.mean(r.reprojection_error_px)),
        fallbacks=int(kept.sum()),
        structure=r.fallback_code.count("structure"),
        worse=worse,
        covered=covered,
        median_dc_px=float(np.median(np.hypot(*dc.T))),
        met=met_reference and worse == 0,
    )


def run_suite(root: Path, model, progress: Callable = iter, note: Callable[[str], None] = _stderr_line) -> list:
    """Every (set, lens, mode) row of the suite on the photos under ``root`` with ``model`` (an
    ``OnnxModel``); a set whose photos are missing is left out (``missing_sets``); ``progress``
    wraps the sets' iteration (a progress bar); ``note`` takes one line per photo ingest drops (by
    default on stderr)."""
    rows = []
    for s in progress([s for s in SETS if s.name not in missing_sets(root)]):
        try:
            ds = _ingested(root, s, note)
            cameras = _cameras(ds, s)
        except DimenetError as exc:
            rows += [SuiteRow(s.name, lens, mode, problem=str(exc)) for lens in (False, True) for mode in MODES]
            continue
        for lens, (camera, K_star) in zip((False, True), cameras):
            for mode in MODES:
                try:
                    rows.append(_row(s, ds, camera, K_star, model, mode, lens))
                except DimenetError as exc:
                    rows.append(SuiteRow(s.name, lens, mode, problem=str(exc)))
    return rows


def format_suite(rows: list) -> str:
    """The suite's table, one line per row, and a last line with how many rows met their targets."""
    head = f"{'set':<12} {'lens':<7} {'mode':<8} {'frames':>6} {'e_c px':>7} {'e px':>7} {'K_c kept':>8} "
    head += f"{'structure':>9} {'e>e_c':>5} {'2σ':>5} {'|Δc| px':>8}  target"
    lines = [head]
    for r in rows:
        lens = LENS_MODEL if r.lens else "none"
        if r.problem is not None:
            lines.append(f"{r.set_name:<12} {lens:<7} {r.mode:<8} error: {r.problem}")
            continue
        lines.append(
            f"{r.set_name:<12} {lens:<7} {r.mode:<8} {r.frames:>6} {r.avg_e_c_px:>7.3f} {r.avg_e_px:>7.3f} "
            f"{r.fallbacks:>8} {r.structure:>9} {r.worse:>5} {r.covered:>5.0%} {r.median_dc_px:>8.1f}  "
            f"{'met' if r.met else 'MISSED'}"
        )
    lines.append(f"{sum(r.met for r in rows)} of {len(rows)} rows meet their targets")
    return "\n".join(lines)
