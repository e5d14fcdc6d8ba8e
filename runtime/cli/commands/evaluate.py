"""`dimenet evaluate`: e_c, e* (and e, rho with a model) per scene on one split; with
``--methods``, one row per method (kc, platform, self, dimenet, map, map+platform, oracle) and scene.
A dataset with lens distortion (``dist_coeffs``) is evaluated on its undistorted points
(``Dataset.undistorted``): K, e and rho are those of its pinhole camera. ``--suite real``: the
real-photo suite (``bench.real_suite``) instead of a dataset."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dimenet.runtime.bench.real_suite import SETS, format_suite, missing_sets, run_suite
from dimenet.runtime.cli.arguments import finite_float_in, grid_size, integer_in, noise_sigma, nonempty_path, seed
from dimenet.runtime.cli.camera_option import add_camera_argument, dataset_camera_file, served_camera
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.evaluation.conditions import add_noise, drop_inference_points, empty_cells
from dimenet.runtime.evaluation.methods import (
    ALL_METHODS,
    MODEL_METHODS,
    RUNTIME_METHODS,
    evaluate,
    format_table,
    require_platform,
    with_prior_oracle,
)
from dimenet.runtime.evaluation.predictor import load_predictor
from dimenet.runtime.formats.dataset import SPLITS, read_dataset
from dimenet.runtime.geometry import MIN_POINTS
from dimenet.runtime.jobs.progress import progress
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import BUNDLED_HELP, DEFAULT_NAME, load_model

# The real-photo suite's sets, beside the project's folder as the tests find them.
DEFAULT_PHOTOS = "../shared/real-photos"
MAX_DROP = 10**6  # points kept per frame; more than a frame has keeps them all


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "data",
        nargs="?",
        help="dataset file (dimenet-dataset/1 .npz); one with lens distortion is evaluated on its undistorted points",
    )
    p.add_argument(
        "--suite",
        choices=("real",),
        help="instead of a dataset: the real-photo suite, public photo sets ingested, calibrated with and without "
        "a lens and rectified in both modes against the do-no-harm targets (models_spec/real-photos.md); "
        "exit 1 when a target is missed",
    )
    p.add_argument(
        "--photos",
        type=nonempty_path,
        metavar="DIR",
        help=f"the suite's photo sets (default {DEFAULT_PHOTOS}, skipped with a reason when absent)",
    )
    p.add_argument(
        "--model",
        type=nonempty_path,
        help="trained model: a RUN_DIR from `dimenet train`, a .onnx from `dimenet export`, or a bundled model: "
        + BUNDLED_HELP,
    )
    add_camera_argument(p)
    p.add_argument("--split", default="test", choices=SPLITS, help="frames to evaluate (default: test)")
    p.add_argument(
        "--drop",
        type=integer_in(MIN_POINTS, MAX_DROP),
        metavar="N",
        help="keep N uniformly drawn inference points per frame",
    )
    p.add_argument("--noise-2d", type=noise_sigma, default=0.0, metavar="PX", help="extra 2D Gaussian noise, px")
    p.add_argument("--noise-3d", type=noise_sigma, default=0.0, metavar="MM", help="extra 3D Gaussian noise, mm")
    p.add_argument(
        "--eta",
        type=finite_float_in(0.0, 1.0, below=True),
        default=0.0,
        metavar="FRACTION",
        help="empty this fraction of the occupied grid cells (paper Table 2)",
    )
    p.add_argument("--grid", type=grid_size, help="grid (columns x rows) for --eta (default: the model's, else 8x6)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the test conditions (default 0)")
    p.add_argument(
        "--methods",
        type=_methods,
        default=(),
        metavar="M1,M2",
        help=f"compare methods, comma-separated from {','.join(ALL_METHODS + RUNTIME_METHODS)} (dimenet and map, "
        "the paper's protocol: the network's K on every frame; rectify and rectify-map: the product as `dimenet "
        "rectify` runs it, with its fallback rules; these need --model; platform needs the dataset's K_platform): "
        "rho per method and scene, and the 1-sigma coverage of K's uncertainty; with a mode on natural frames the "
        "prior oracle (prior-oracle: the MAP fit under the true population prior of K and the true label noise, "
        "which needs the dataset's K_true and label_noise_px) comes beside it, with each method's rho over its own "
        "and a 90%% interval",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def _methods(text: str) -> tuple:
    names = tuple(m.strip() for m in text.split(",") if m.strip())
    known = ALL_METHODS + RUNTIME_METHODS
    unknown = [m for m in names if m not in known]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown method {unknown[0] if unknown else text!r} (choose from {','.join(known)})"
        )
    return names


def run(args: argparse.Namespace) -> int:
    if args.suite is not None:
        return _run_suite(args)
    if args.data is None:
        raise CliError("give a dataset file, or --suite real")
    if args.photos is not None:
        raise CliError("--photos goes with --suite real")
    needs_model = [m for m in args.methods if m in MODEL_METHODS]
    if needs_model and not args.model:
        raise CliError(f"--methods {needs_model[0]} needs --model")
    ds = read_dataset(args.data).undistorted()
    require_platform(ds, args.methods)
    predictor = load_predictor(args.model) if args.model else None
    if predictor is not None:
        predictor = predictor.for_camera(served_camera(predictor.spec, ds, args.camera, predictor.source))
        K_c = predictor.K_c
    else:
        K_c = dataset_camera_file(args.camera, ds).K if args.camera else calibrate_dataset(ds).K_c
    grid = Grid.parse(args.grid) if args.grid else (predictor.spec.features.grid if predictor else Grid(8, 6))
    chosen = ds.frames_in(args.split)
    if not chosen.any():
        raise DatasetError(f"split: the dataset has no {args.split!r} frames")
    frames = ds.select(chosen)
    rng = np.random.default_rng(args.seed)
    if args.noise_2d or args.noise_3d:
        frames = add_noise(frames, args.noise_2d, args.noise_3d, rng)
    if args.drop is not None:
        frames = drop_inference_points(frames, args.drop, rng)
    if args.eta:
        frames = empty_cells(frames, args.eta, grid, rng)
    # Beside the modes on natural frames: the prior oracle (what one frame allows), or why it is missing.
    methods, missing = with_prior_oracle(frames, args.methods)
    ev = evaluate(frames, K_c, predictor, split=args.split, methods=methods)
    if args.json:
        print(json.dumps({**ev.to_json(), **({"prior_oracle_missing": missing} if missing else {})}))
    else:
        print(format_table(ev) + (f"\n{missing}" if missing else ""))
    return 0


def _run_suite(args: argparse.Namespace) -> int:
    if args.data is not None:
        raise CliError("--suite real runs on its own photo sets: give no dataset file")
    root = Path(args.photos or DEFAULT_PHOTOS)
    missing = missing_sets(root)
    if len(missing) == len(SETS):
        if args.photos is not None:
            raise CliError(f"--photos {root}: none of the suite's sets ({', '.join(s.name for s in SETS)}) is there")
        print(f"real-photo suite skipped: none of its sets is under {root} (give --photos DIR)")
        return 0
    model = load_model(args.model or DEFAULT_NAME)
    rows = run_suite(root, model, progress=lambda sets: progress(sets, total=len(sets), desc="real-photo sets"))
    if args.json:
        print(json.dumps({"root": str(root), "missing": missing, "rows": [r.to_dict() for r in rows]}))
    else:
        print(format_suite(rows))
        if missing:
            print(f"skipped (not under {root}): {', '.join(missing)}")
    return 0 if all(r.met for r in rows) else 1


COMMAND = Command(
    name="evaluate",
    summary="Report Avg(e_c) and Avg(e*) per scene (and Avg(e), rho with a model) on one split, in px.",
    example=(
        "dimenet evaluate s8.npz --model runs/s8 --split test --drop 64 --methods kc,self,dimenet,map,oracle --json\n"
        "  dimenet evaluate --suite real --photos ../shared/real-photos"
    ),
    add_arguments=add_arguments,
    run=run,
)
