"""`dimenet bench`: latency of the runtime against cv2.solvePnP ITERATIVE under K_c (see runtime/bench.py)."""

from __future__ import annotations

import argparse
import json

from dimenet.runtime.cli.main import Command, positive_float
from dimenet.runtime.evaluation.latency import format_report, run_bench


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", help="a .onnx from `dimenet export` (default: the bundled model)")
    p.add_argument("--points", type=int, default=320, help="correspondences per frame (default 320)")
    p.add_argument("--frames", type=int, default=2000, help="frames to time (default 2000)")
    p.add_argument("--threads", type=int, default=1, help="ONNX Runtime and OpenCV threads (default 1)")
    p.add_argument("--batch", type=int, default=1, help="also time rectify_batch on batches of B frames")
    p.add_argument("--budget-ms", type=positive_float, metavar="X", help="exit 1 when the end-to-end p99 exceeds X ms")
    p.add_argument("--refine", action="store_true", help="polish poses with cv2.solvePnPRefineLM")
    p.add_argument(
        "--mode",
        choices=("dimenet", "map"),
        default="dimenet",
        help="rectification mode: the paper's method or the MAP fusion with the frame (default dimenet)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def run(args: argparse.Namespace) -> int:
    report = run_bench(
        args.model,
        frames=args.frames,
        points=args.points,
        threads=args.threads,
        batch=args.batch,
        refine=args.refine,
        mode=args.mode,
    )
    over = args.budget_ms is not None and report["end_to_end_us"]["p99"] > 1e3 * args.budget_ms
    if args.budget_ms is not None:
        report["budget_ms"], report["within_budget"] = args.budget_ms, not over
    print(json.dumps(report, indent=1) if args.json else format_report(report))
    if over and not args.json:
        print(f"end-to-end p99 {report['end_to_end_us']['p99'] / 1e3:.3f} ms exceeds the budget of {args.budget_ms} ms")
    return 1 if over else 0


COMMAND = Command(
    name="bench",
    summary="Time rectification per stage and end to end (p50/p90/p99/max, µs) against cv2.solvePnP ITERATIVE.",
    example="dimenet bench --points 320 --frames 2000 --threads 1 --batch 64 --budget-ms 0.5 --json",
    add_arguments=add_arguments,
    run=run,
)
