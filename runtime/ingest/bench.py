"""Measure `dimenet ingest` on rendered full-size photos of the paper's rig against the renderer's truth.

    python -m dimenet.runtime.ingest.bench DIR [--n 30] [--seed 1] [--profile galaxy-s8] [--workers 2] [--json]

Renders ``--n`` photos into DIR first unless DIR already holds a ``truth.npz``; then ingests them
(timed: photos/s) and prints the detection rate, identity errors, corner RMS against the true
projections and the mean |K* - K_true| of the ingested frames (``render_truth.score``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

from dimenet.runtime.formats.rig import paper_rig
from dimenet.runtime.ingest.pipeline import ingest
from dimenet.runtime.sim.render import TRUTH_FILE, write_render
from dimenet.runtime.sim.render_truth import read_truth, score
from dimenet.runtime.sim.simulator import PROFILES, get_profile


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m dimenet.runtime.ingest.bench", description=__doc__.splitlines()[0])
    p.add_argument("dir", help="folder of rendered photos (rendered there first if it has no truth.npz)")
    p.add_argument("--n", type=int, default=30, help="photos to render (default 30)")
    p.add_argument("--seed", type=int, default=1, help="render seed (default 1)")
    p.add_argument("--profile", choices=sorted(PROFILES), default="galaxy-s8")
    p.add_argument("--workers", type=int, default=2, help="ingest worker processes (default 2)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    folder = Path(args.dir)
    rig = paper_rig()
    if not (folder / TRUTH_FILE).is_file():
        write_render(folder, rig, get_profile(args.profile), args.n, seed=args.seed)
    truth = read_truth(folder / TRUTH_FILE)
    start = time.monotonic()
    result = ingest([folder / str(f) for f in truth.frame_id], rig, workers=args.workers)
    seconds = time.monotonic() - start
    s = score(result.dataset, truth)
    figures = {
        **asdict(s),
        "detection_rate": s.detection_rate,
        "workers": args.workers,
        "seconds": seconds,
        "photos_per_s": s.photos / seconds,
    }
    if args.json:
        print(json.dumps(figures))
    else:
        print(
            f"{s.photos} photos, {s.frames} frames: boards found {s.boards_found}/{s.boards_shown} "
            f"({100 * s.detection_rate:.1f} %, + {s.extra_boards} not counted as whole), identity errors "
            f"{s.identity_errors}, corner RMS {s.corner_rms_px:.3f} px (max {s.corner_max_px:.3f}), "
            f"mean |K* - K_true| {s.k_error_px:.3f} px, {figures['photos_per_s']:.2f} photos/s "
            f"with {args.workers} workers"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
