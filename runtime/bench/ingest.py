"""Measure `dimenet ingest`: on rendered photos of the paper's rig against the renderer's truth, or on real photos.

    dimenet bench --ingest DIR [--n 30] [--seed 1] [--profile galaxy-s8] [--workers 2] [--json]

Rendered: renders ``n`` photos into DIR first (a new or empty folder) unless DIR already holds a
``truth.npz`` (then the photos it names, whatever their size, e.g. ``dimenet render --scale 2.52``
for 1600x1200; an --n, --seed or --profile given that its photos were not rendered with is an
IngestError, never a silent reuse); then ingests them (timed: photos/s) and reports the detection rate, identity errors,
corner RMS against the true projections and the mean |K* - K_true| of the ingested frames
(``bench.ingest_score.score``).

Real: a DIR without ``truth.npz`` but with a rig file ``rig.json`` (``dimenet-rig/1``) beside its photos
(every JPEG, PNG, TIFF, WebP, BMP or PNM in it, by name): ingests them with that rig (timed) and reports
the frames, the boards identified per photo and each photo's K (no truth to score against).
A folder that holds files but neither is refused: rendering into it would mix the renders with them.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

from dimenet.runtime.bench.ingest_score import score
from dimenet.runtime.errors import DatasetError, IngestError
from dimenet.runtime.formats.render_truth import Truth, read_truth
from dimenet.runtime.formats.rig import load_rig, paper_rig
from dimenet.runtime.geometry import k_params
from dimenet.runtime.ingest.pipeline import ingest
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, write_render

RIG_FILE = "rig.json"  # the rig of a folder of real photos
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp", ".bmp", ".pbm", ".pgm", ".ppm")


def run_real_bench(folder: Path, *, workers: int) -> dict:
    """Ingest (timed) the photos of a folder of real photos with its ``rig.json``; the figures."""
    rig = load_rig(folder / RIG_FILE)
    photos = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    start = time.monotonic()
    result = ingest(photos, rig, workers=workers)
    seconds = time.monotonic() - start
    return {
        "photos": len(photos),
        "frames": 0 if result.dataset is None else result.dataset.n_frames,
        "boards": {r.name: [rig.boards[b].name for b in r.boards] for r in result.results},
        "boards_in_rig": len(rig.boards),
        "K_px": {r.name: None if r.K is None else [round(float(v), 2) for v in k_params(r.K)] for r in result.results},
        "workers": workers,
        "seconds": seconds,
        "photos_per_s": len(photos) / seconds,
    }


def rendered_with(truth: Truth, truth_file: Path) -> dict:
    """The n, seed and profile a render's truth (read from ``truth_file``) was written with (its ``meta``)."""
    try:
        return {"n": len(truth.frame_id), "seed": int(truth.meta["seed"]), "profile": str(truth.meta["profile"])}
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{truth_file}: its meta does not say how the photos were rendered ({exc})") from None


def run_ingest_bench(folder, *, n: int, seed: int, profile: str, workers: int, asked: Optional[dict] = None) -> dict:
    """Rendered: render (unless there already) and ingest the photos of ``folder``; the scored figures.
    ``asked``: the render options the user gave ({"seed": 1, ...}); photos already in ``folder``
    rendered otherwise are an IngestError. Real (a folder with ``rig.json`` and no truth): ``run_real_bench``."""
    folder = Path(folder)
    if not (folder / TRUTH_FILE).is_file() and (folder / RIG_FILE).is_file():
        return run_real_bench(folder, workers=workers)
    rig = paper_rig()
    if not (folder / TRUTH_FILE).is_file():
        if folder.is_dir() and any(folder.iterdir()):
            raise IngestError(
                f"{folder}: holds files but neither {TRUTH_FILE} (rendered photos) nor {RIG_FILE} (real photos "
                "and their rig); give an empty or new folder to render into"
            )
        write_render(folder, rig, get_profile(profile), n, seed=seed)
    truth = read_truth(folder / TRUTH_FILE)
    if asked:
        done = rendered_with(truth, folder / TRUTH_FILE)
        wrong = {k: v for k, v in asked.items() if done[k] != v}
        if wrong:
            asked_text = ", ".join(f"--{k} {v}" for k, v in wrong.items())
            done_text = ", ".join(f"--{k} {done[k]}" for k in wrong)
            raise IngestError(
                f"{folder}: holds photos rendered with {done_text}, not {asked_text}: give a new folder to render "
                "into, or the options they were rendered with"
            )
    start = time.monotonic()
    result = ingest([folder / str(f) for f in truth.frame_id], rig, workers=workers)
    seconds = time.monotonic() - start
    s = score(result.dataset, truth)
    return {
        **asdict(s),
        "detection_rate": s.detection_rate,
        "workers": workers,
        "seconds": seconds,
        "photos_per_s": s.photos / seconds,
    }


def format_ingest_report(figures: dict) -> str:
    """One line of the figures of ``run_ingest_bench``."""
    f = figures
    if "boards_shown" not in f:
        per_photo = sum(len(b) for b in f["boards"].values())
        return (
            f"{f['photos']} real photos, {f['frames']} frames: {per_photo} boards identified "
            f"({per_photo / max(f['photos'], 1):.2f} per photo, the rig has {f['boards_in_rig']}), "
            f"{f['photos_per_s']:.2f} photos/s with {f['workers']} workers"
        )
    return (
        f"{f['photos']} photos, {f['frames']} frames: boards found {f['boards_found']}/{f['boards_shown']} "
        f"({100 * f['detection_rate']:.1f} %, + {f['extra_boards']} not counted as whole), identity errors "
        f"{f['identity_errors']}, corner RMS {f['corner_rms_px']:.3f} px (max {f['corner_max_px']:.3f}), "
        f"mean |K* - K_true| {f['k_error_px']:.3f} px, {f['photos_per_s']:.2f} photos/s "
        f"with {f['workers']} workers"
    )
