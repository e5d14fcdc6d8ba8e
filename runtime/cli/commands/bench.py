"""`dimenet bench`: latency of the runtime against cv2.solvePnP ITERATIVE under K_c
(runtime/bench/latency.py); with ``--ingest DIR``, `dimenet ingest` on rendered full-size
photos against the renderer's truth (runtime/bench/ingest.py); with ``--bpnp``, forward +
backward of the BPnP layer against a BPnP_fast-style baseline (the ``bpnp`` entry point of the
``dimenet.benches`` group, training/bench_bpnp.py: needs the train extra, loaded only then, so the
runtime never imports torch or the training package); with ``--fuzz N``, hostile input through the
rectifier, the readers and, where onnx is installed, the full graph and the .ort loader
(runtime/bench/fuzz.py); with ``--stream N``, `dimenet rectify --points` on an N-frame points CSV of the
bundled example's frames: frames/s and peak memory (runtime/bench/streaming.py)."""

from __future__ import annotations

import argparse
import json

from dimenet.runtime.bench.latency import format_report, run_bench
from dimenet.runtime.cli.arguments import finite_float_in, integer_in, nonempty_path, parallelism, seed
from dimenet.runtime.cli.commands.render import MAX_PHOTOS
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.geometry import MIN_POINTS
from dimenet.runtime.plugins import entry_points
from dimenet.runtime.rectify.model import BUNDLED_HELP
from dimenet.runtime.sim.profiles import PROFILES

# Each bench's options and their defaults. The parser's defaults are None, so that an option
# given to a bench it does not belong to is refused instead of ignored.
LATENCY = {
    "model": None,
    "mode": "dimenet",
    "points": 320,
    "frames": 2000,
    "threads": 1,
    "batch": 1,
    "callers": 1,
    "budget_ms": None,
    "refine": False,
}
INGEST = {"n": 30, "seed": 1, "profile": "galaxy-s8", "workers": 2}
BPNP = {"frames": 32, "points": 320, "repeats": 200, "baseline_repeats": 10}
FUZZ = {"seed": 0, "model": None}
STREAM: dict = {}  # --stream N alone
# Caps: --frames x --points correspondences are held in memory (50000 x 320: 0.6 GB); the BPnP
# baseline's Jacobian is 2N x 3N floats per frame (N = 2000: 96 MB), its layer B x N x 20.
MAX_FRAMES = 50_000
MAX_POINTS = 100_000  # the latency bench's frames have at most 320 (refused with the count)
MAX_BPNP_POINTS = 2_000
MAX_BPNP_CORRESPONDENCES = 10**6  # --frames x --points with --bpnp
MAX_REPEATS = 100_000
MAX_BUDGET_MS = 60_000.0  # a minute per frame: past it a budget is a typo
MAX_FUZZ_CASES = 100_000
MAX_STREAM_FRAMES = 200_000  # the temp CSV takes ~16 KB per frame: 3.2 GB at the cap
BENCHES = {
    "the latency bench (without --ingest, --bpnp, --fuzz or --stream)": LATENCY,
    "--ingest": INGEST,
    "--bpnp": BPNP,
    "--fuzz": FUZZ,
    "--stream": STREAM,
}


def _default(name: str) -> str:
    """The help's "default X" of a latency option, with its --bpnp default where that differs."""
    bpnp = f"; with --bpnp {BPNP[name]}" if name in BPNP and BPNP[name] != LATENCY[name] else ""
    return f"default {LATENCY[name]}{bpnp}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    latency = p.add_argument_group(
        "latency bench (the default)", "the runtime's stages and end to end against cv2.solvePnP ITERATIVE under K_c"
    )
    latency.add_argument(
        "--model",
        type=nonempty_path,
        help=f"a .onnx from `dimenet export`, or a bundled model: {BUNDLED_HELP}; "
        "with --fuzz, the model the hostile frames go through",
    )
    latency.add_argument(
        "--points", type=integer_in(MIN_POINTS, MAX_POINTS), help=f"correspondences per frame ({_default('points')})"
    )
    latency.add_argument("--frames", type=integer_in(1, MAX_FRAMES), help=f"frames to time ({_default('frames')})")
    latency.add_argument("--threads", type=parallelism, help=f"ONNX Runtime and OpenCV threads ({_default('threads')})")
    latency.add_argument(
        "--batch", type=integer_in(1, MAX_FRAMES), help="also time rectify_batch on batches of B frames"
    )
    latency.add_argument(
        "--callers",
        type=parallelism,
        metavar="C",
        help="also time C Python threads calling rectify on one shared Rectifier (with --threads 1: issue 49's "
        "two-caller figure)",
    )
    latency.add_argument(
        "--budget-ms",
        type=finite_float_in(0.0, MAX_BUDGET_MS, above=True),
        metavar="X",
        help="exit 1 when the end-to-end p99 exceeds X ms",
    )
    latency.add_argument("--refine", action="store_true", default=None, help="polish poses with cv2.solvePnPRefineLM")
    latency.add_argument(
        "--mode",
        choices=("dimenet", "map"),
        help=f"rectification mode: the paper's method or the MAP fusion with the frame ({_default('mode')})",
    )
    ingest = p.add_argument_group(
        "ingest bench (--ingest DIR)",
        "`dimenet ingest` on rendered full-size photos of the paper's rig, scored against the truth",
    )
    ingest.add_argument(
        "--ingest",
        type=nonempty_path,
        metavar="DIR",
        help="folder of rendered photos (rendered there first if it has no truth.npz)",
    )
    ingest.add_argument("--n", type=integer_in(1, MAX_PHOTOS), help=f"photos to render (default {INGEST['n']})")
    ingest.add_argument("--seed", type=seed, help=f"render seed (default {INGEST['seed']})")
    ingest.add_argument("--profile", choices=sorted(PROFILES), help=f"device profile (default {INGEST['profile']})")
    ingest.add_argument(
        "--workers", type=parallelism, help=f"ingest workers: two threads, then processes (default {INGEST['workers']})"
    )
    bpnp = p.add_argument_group(
        "BPnP bench (--bpnp; needs the train extra)",
        "forward + backward of the training's BPnP layer on B frames x N points (--frames, --points), "
        "1 thread, against a BPnP_fast-style baseline",
    )
    bpnp.add_argument("--bpnp", action="store_true", help="time the BPnP layer instead of the runtime")
    bpnp.add_argument(
        "--repeats", type=integer_in(1, MAX_REPEATS), help=f"timed runs of the layer (default {BPNP['repeats']})"
    )
    bpnp.add_argument(
        "--baseline-repeats",
        type=integer_in(1, MAX_REPEATS),
        help=f"timed runs of the baseline (default {BPNP['baseline_repeats']})",
    )
    _add_fuzz(p)
    stream = p.add_argument_group(
        "stream (--stream N)",
        "`dimenet rectify --points` on a temp CSV of N frames tiled from the bundled example (its camera, the "
        "bundled model; ~16 KB of disk per frame): frames/s, and the peak RSS after 10 % and 100 % of the stream",
    )
    stream.add_argument("--stream", type=integer_in(1, MAX_STREAM_FRAMES), metavar="N", help="frames to stream")


def _add_fuzz(p: argparse.ArgumentParser) -> None:
    fuzz = p.add_argument_group(
        "fuzz (--fuzz N)",
        "N hostile frames through the rectifier (modes dimenet and map, one by one and in batches), N hostile "
        "streams (times, per-frame K_c, motion samples, options, frames) and N "
        "mutated files of each kind (dataset, model, rig) through their readers: each must end in a typed "
        "error or in no confident wrong K; with onnx, N frames through the model's full graph (within the "
        "parity bound of the runtime, masked garbage and no point included), and with torch too N mutated "
        ".ort files (a typed error or the original's Delta K); exit 1 when one does not (--seed and --model apply)",
    )
    fuzz.add_argument("--fuzz", type=integer_in(1, MAX_FUZZ_CASES), metavar="N", help="cases per area")


def _options(args: argparse.Namespace, bench: dict) -> dict:
    """The options of one bench, defaults filled in; one of another bench given is a CliError."""
    for name in dict.fromkeys(n for options in BENCHES.values() for n in options):
        if name not in bench and getattr(args, name) is not None:
            owners = " or ".join(phrase for phrase, options in BENCHES.items() if name in options)
            raise CliError(f"dimenet bench: --{name.replace('_', '-')} applies only to {owners}")
    return {name: default if getattr(args, name) is None else getattr(args, name) for name, default in bench.items()}


def run(args: argparse.Namespace) -> int:
    chosen = [
        flag
        for flag, on in zip(
            ("--ingest", "--bpnp", "--fuzz", "--stream"), (args.ingest is not None, args.bpnp, args.fuzz, args.stream)
        )
        if on
    ]
    if len(chosen) > 1:
        raise CliError(f"dimenet bench: {' and '.join(chosen)} exclude each other")
    if args.ingest is not None:
        return _run_ingest(args)
    if args.bpnp:
        return _run_bpnp(args)
    if args.fuzz:
        return _run_fuzz(args)
    if args.stream:
        return _run_stream(args)
    return _run_latency(args)


def _run_stream(args: argparse.Namespace) -> int:
    import tempfile
    from importlib import resources

    from dimenet.runtime.assets import asset
    from dimenet.runtime.bench.streaming import format_stream_report, run_stream_bench
    from dimenet.runtime.cli.commands.rectify import EXAMPLE_CAMERA, EXAMPLE_DATA
    from dimenet.runtime.formats.camera_file import read_camera
    from dimenet.runtime.formats.dataset import read_dataset

    _options(args, STREAM)
    with resources.as_file(asset(EXAMPLE_DATA)) as data, resources.as_file(asset(EXAMPLE_CAMERA)) as camera:
        frames, camera = read_dataset(data), read_camera(camera)
    with tempfile.TemporaryDirectory() as folder:
        figures = run_stream_bench(folder, args.stream, frames, camera)
    print(json.dumps(figures) if args.json else format_stream_report(figures))
    return 0


def _run_fuzz(args: argparse.Namespace) -> int:
    import tempfile

    import numpy as np

    from dimenet.runtime.bench.fuzz import FuzzReport, fuzz_files, fuzz_full_graph, fuzz_ort_file, fuzz_rectifier
    from dimenet.runtime.bench.fuzz_stream import fuzz_streams
    from dimenet.runtime.bench.latency import bench_rectifier
    from dimenet.runtime.errors import DimenetError
    from dimenet.runtime.rectify.model import load_model, resolve_model
    from dimenet.runtime.sim.simulator import simulate

    o = _options(args, FUZZ)
    rng = np.random.default_rng(o["seed"])
    # Rig frames for the rectifier (the other scenes change none of them), every scene for the full graph.
    frames = simulate("galaxy-s8", seed=o["seed"], natural_frames=6, planar_frames=6)
    report = FuzzReport()
    model = load_model(o["model"])
    for mode in ("dimenet", "map"):
        fuzz_rectifier(bench_rectifier(model, mode, frames), frames, args.fuzz, rng, report)
    fuzz_streams(bench_rectifier(model, "dimenet", frames), frames, args.fuzz, rng, report)
    with tempfile.TemporaryDirectory() as folder:
        fuzz_files(folder, args.fuzz, rng, report)
    blob = resolve_model(o["model"]).model_bytes()
    graph = _skipped("full graph", ("onnx",), "export")
    if not graph and model.spec.generic is None:
        graph = f"full graph: skipped, {model.source} is a device model (the full graph holds generic models)"
    if not graph:
        fuzz_full_graph(blob, model.source, frames, args.fuzz, rng, report)
    ort_file = _skipped(".ort file", ("torch", "onnx"), "train")  # the .ort conversion sits beside the torch export
    if not ort_file:  # last: the .ort format's checks
        try:
            fuzz_ort_file(blob, model.source, args.fuzz, rng, report)
        except DimenetError as exc:  # a model the conversion refuses (a spec before 1.9)
            ort_file = f".ort file: skipped, {exc}"
    skipped = [line for line in (graph, ort_file) if line]
    counts = {area: dict(c) for area, c in report.counts.items()}
    if args.json:
        print(json.dumps({"model": model.source, "counts": counts, "failures": report.failures, "skipped": skipped}))
    else:
        print("\n".join([f"model {model.source}", report.table(), *skipped]))
    return 1 if report.bad else 0


def _skipped(area: str, modules: tuple, extra: str) -> str:
    """'' when ``modules`` are installed, else the line saying the fuzz skips ``area`` and the install it needs."""
    from importlib.util import find_spec

    from dimenet.runtime.cli.extras import install_command

    missing = [m for m in modules if find_spec(m) is None]
    if not missing:
        return ""
    return f"{area}: skipped, it needs {' and '.join(missing)} (the {extra} extra): {install_command((extra,))}"


def _run_latency(args: argparse.Namespace) -> int:
    o = _options(args, LATENCY)
    report = run_bench(
        o["model"],
        frames=o["frames"],
        points=o["points"],
        threads=o["threads"],
        batch=o["batch"],
        callers=o["callers"],
        refine=o["refine"],
        mode=o["mode"],
    )
    budget = o["budget_ms"]
    over = budget is not None and report["end_to_end_us"]["p99"] > 1e3 * budget
    if budget is not None:
        report["budget_ms"], report["within_budget"] = budget, not over
    print(json.dumps(report, indent=1) if args.json else format_report(report))
    if over and not args.json:
        print(f"end-to-end p99 {report['end_to_end_us']['p99'] / 1e3:.3f} ms exceeds the budget of {budget} ms")
    return 1 if over else 0


def _run_ingest(args: argparse.Namespace) -> int:
    from dimenet.runtime.bench.ingest import format_ingest_report, run_ingest_bench

    o = _options(args, INGEST)
    asked = {name: getattr(args, name) for name in ("n", "seed", "profile") if getattr(args, name) is not None}
    figures = run_ingest_bench(args.ingest, **o, asked=asked)
    print(json.dumps(figures) if args.json else format_ingest_report(figures))
    return 0


def _run_bpnp(args: argparse.Namespace) -> int:
    o = _options(args, BPNP)
    if o["points"] > MAX_BPNP_POINTS:
        raise CliError(f"dimenet bench: --points must be <= {MAX_BPNP_POINTS} with --bpnp, got {o['points']}")
    if o["frames"] * o["points"] > MAX_BPNP_CORRESPONDENCES:
        raise CliError(
            f"dimenet bench: --frames x --points must be <= {MAX_BPNP_CORRESPONDENCES} with --bpnp, "
            f"got {o['frames']} x {o['points']}"
        )
    bench = _bpnp_bench()
    result = bench.run(o["frames"], o["points"], o["repeats"], o["baseline_repeats"])
    print(json.dumps(result, indent=2) if args.json else bench.format_report(result))
    return 0


def _bpnp_bench():
    """The BPnP bench the train extra registers as ``bpnp`` in ``dimenet.benches``: a module with
    ``run(frames, points, repeats, baseline_repeats) -> dict`` and ``format_report(dict) -> str``."""
    from dimenet.runtime.cli.extras import install_command

    entry = entry_points("dimenet.benches").get("bpnp")
    if entry is None:  # an installation without the training package's entry points
        raise CliError(f"dimenet bench --bpnp: no bpnp bench is registered: {install_command(('train',))}")
    return entry.load()


COMMAND = Command(
    name="bench",
    summary="Time rectification per stage and end to end (p50/p90/p99/max, µs) against cv2.solvePnP ITERATIVE; "
    "--ingest: photo ingest against the renderer's truth; --bpnp: the BPnP layer; --fuzz: hostile input; "
    "--stream: rectify --points throughput and memory.",
    example="dimenet bench --points 320 --frames 2000 --threads 1 --batch 64 --budget-ms 10 --json   # exit 1 past "
    "a 10 ms p99 (a 2-core VM: 0.6-4.4 ms)\n"
    "  dimenet bench --ingest bench-shots --n 30 --seed 1 --profile galaxy-s8 --workers 2   # renders there first\n"
    "  dimenet bench --bpnp --frames 32 --points 320 --repeats 200\n"
    "  dimenet bench --fuzz 2000 --seed 1 --model paper-rig\n"
    "  dimenet bench --stream 100000",
    add_arguments=add_arguments,
    run=run,
)
