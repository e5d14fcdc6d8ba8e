"""Measure `dimenet ingest` on rendered full-size photos of the paper's rig against the renderer's truth.

    dimenet bench --ingest DIR [--n 30] [--seed 1] [--profile galaxy-s8] [--workers 2] [--json]

Renders ``n`` photos into DIR first unless DIR already holds a ``truth.npz``; then ingests them
(timed: photos/s) and reports the detection rate, identity errors, corner RMS against the true
projections and the mean |K* - K_true| of the ingested frames (``render_truth.score``).
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

from dimenet.runtime.formats.rig import paper_rig
from dimenet.runtime.ingest.pipeline import ingest
from dimenet.runtime.sim.render import TRUTH_FILE, write_render
from dimenet.runtime.sim.render_truth import read_truth, score
from dimenet.runtime.sim.simulator import get_profile


def run_ingest_bench(folder, *, n: int, seed: int, profile: str, workers: int) -> dict:
    """Render (unless there already) and ingest the photos of ``folder``; the scored figures."""
    folder = Path(folder)
    rig = paper_rig()
    if not (folder / TRUTH_FILE).is_file():
        write_render(folder, rig, get_profile(profile), n, seed=seed)
    truth = read_truth(folder / TRUTH_FILE)
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
    return (
        f"{f['photos']} photos, {f['frames']} frames: boards found {f['boards_found']}/{f['boards_shown']} "
        f"({100 * f['detection_rate']:.1f} %, + {f['extra_boards']} not counted as whole), identity errors "
        f"{f['identity_errors']}, corner RMS {f['corner_rms_px']:.3f} px (max {f['corner_max_px']:.3f}), "
        f"mean |K* - K_true| {f['k_error_px']:.3f} px, {f['photos_per_s']:.2f} photos/s "
        f"with {f['workers']} workers"
    )
