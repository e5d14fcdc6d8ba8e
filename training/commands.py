"""`dimenet train` (and the other torch-side subcommands). Torch is imported only when run."""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

from dimenet.runtime.cli.arguments import grid_size, nonempty_path, seed
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import BUNDLED_HELP
from dimenet.runtime.rectify.spec import HEADS

from .config import (
    FEATURE_VARIANTS,
    QUICK_CAMERAS,
    QUICK_EPOCHS,
    ReproduceConfig,
    TrainConfig,
    epochs,
    focal_weight,
    k_c_error,
    plane_share,
    train_frames,
)

# The defaults --help states are the dataclasses' own (training/config.py imports no torch).
TRAIN_DEFAULTS = TrainConfig()
REPRODUCE_DEFAULTS = {f.name: f.default for f in dataclasses.fields(ReproduceConfig) if f.name != "out_dir"}


class _Noted(argparse.Action):
    """Stores a flag's value (``const`` for a switch, ``nargs=0``) and notes its dest in the namespace's
    ``given``: the flags an --init model fixes, told apart from their defaults (``_network_settings``)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)
        namespace.given = {*getattr(namespace, "given", ()), self.dest}


def _add_train(p: argparse.ArgumentParser) -> None:
    d = TRAIN_DEFAULTS
    p.add_argument(
        "data",
        nargs="?",
        help="dataset file (dimenet-dataset/1 .npz) with a train split: a device model of its camera; or a folder "
        "of them (a camera family, `dimenet simulate --family`): a generic model for any camera",
    )
    p.add_argument(
        "--out",
        type=nonempty_path,
        metavar="RUN_DIR",
        help="folder for weights, spec.json, curve.png (and, while it trains, checkpoint.safetensors)",
    )
    p.add_argument(
        "--resume",
        type=nonempty_path,
        metavar="RUN_DIR",
        help="instead of DATA --out: continue the training stopped in RUN_DIR from its last finished epoch (its "
        "checkpoint holds the data, init and settings): the same weights, bit for bit, as a training never stopped",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"a smoke run: {QUICK_EPOCHS} epoch, whatever --epochs says (checks that the command runs end to end; "
        "the model learns nothing)",
    )
    p.add_argument(
        "--grid",
        type=grid_size,
        default=str(d.features.grid),
        action=_Noted,
        help=f"grid, columns x rows (default {d.features.grid})",
    )
    p.add_argument(
        "--features",
        default=d.features.variant,
        action=_Noted,
        choices=FEATURE_VARIANTS,
        help=f"feature variant of paper Table 3 (default {d.features.variant})",
    )
    p.add_argument(
        "--data-step",
        action=_Noted,
        nargs=0,
        const=True,
        default=False,
        help="after the grid, give the network the frame's own Gauss-Newton step on K from the C0 pose and its "
        "posterior sigmas (not the paper's: an encoder that reads how the points fix K, whatever the scene)",
    )
    p.add_argument(
        "--moments",
        action=_Noted,
        nargs=0,
        const=True,
        default=False,
        help="after the grid (and the data step), give the network the point set's moments: how the points spread "
        "over the image and in depth and how the PMD varies over them, whatever their layout (not the paper's)",
    )
    p.add_argument(
        "--head",
        default=d.head,
        action=_Noted,
        choices=HEADS,
        help="the network's output: mlp (the paper's) or gated_step (Delta K = the MLP's plus a learned share of the "
        f"data step; needs --data-step) (default {d.head})",
    )
    p.add_argument(
        "--epochs", type=epochs, default=d.epochs, help=f"epochs (default {d.epochs}; the best val epoch is kept)"
    )
    p.add_argument("--seed", type=seed, default=d.seed, help=f"seed: same seed, same model (default {d.seed})")
    p.add_argument(
        "--focal-weight",
        type=focal_weight,
        default=d.focal_weight,
        metavar="W",
        help="weight of the focal term, the squared error (px^2) of the net's fx, fy against "
        f"each frame's K* (default {d.focal_weight}; 0: the paper's loss alone)",
    )
    p.add_argument(
        "--init",
        metavar="MODEL",
        help=f"fine-tune: start from a model's weights, a bundled model ({BUNDLED_HELP}), a RUN_DIR or a "
        "MODEL.onnx; its grid, features (data step, moments), head and layer sizes are kept (a generic init stays "
        "generic; a flag asking for others is named in a warning)",
    )
    p.add_argument(
        "--k-c-error",
        type=k_c_error,
        default=d.k_c_error,
        metavar="SHARE",
        help="share of the cameras that each epoch train under a factory-like K_c (f off up to 3 %%, c up to 1 %% of "
        f"the width) instead of their calibrated one, so the model corrects a platform's K_c (default {d.k_c_error})",
    )
    p.add_argument(
        "--plane-share",
        type=plane_share,
        default=d.plane_share,
        metavar="SHARE",
        help="share of the training frames whose inference points shrink, each epoch, to one plane's (a single "
        "board or wall, where the points do not fix K; the loss still reads all the frame's points) "
        f"(default {d.plane_share})",
    )
    p.add_argument(
        "--train-frames",
        type=train_frames,
        metavar="N",
        help="keep only the first N train frames of each dataset, in file order (default: all)",
    )


# The flags whose settings an --init model fixes (its features and head are kept): the argparse dest, the
# flag, the FeatureSpec field (TrainConfig's for the head).
INIT_FIXES = (
    ("grid", "--grid", "grid"),
    ("features", "--features", "variant"),
    ("data_step", "--data-step", "data_step"),
    ("moments", "--moments", "moments"),
    ("head", "--head", "head"),
)


def _network_settings(args: argparse.Namespace, init) -> dict:
    """TrainConfig's features and head: the flags' (or their defaults) without an init; the init's with one, and
    a warning line on stderr for each flag of INIT_FIXES given another value."""
    if init is None:
        f = {field: getattr(args, dest) for dest, _, field in INIT_FIXES}
        head = f.pop("head")
        return {"features": FeatureSpec(**{**f, "grid": Grid.parse(f["grid"])}), "head": head}
    f = init.spec.features
    kept = {"grid": str(f.grid), "variant": f.variant, "data_step": f.data_step, "moments": f.moments}
    kept["head"] = init.spec.head
    # what the init keeps, where a flag asks for another (a switch given is on, so the init's is off)
    its = {
        "grid": f"grid, {kept['grid']}",
        "variant": f"feature variant, {kept['variant']}",
        "data_step": "feature, without the data step",
        "moments": "feature, without the moments",
        "head": f"head, {kept['head']}",
    }
    given = getattr(args, "given", set())
    for dest, flag, field in INIT_FIXES:
        value = getattr(args, dest)
        if dest in given and value != kept[field]:
            shown = "" if value is True else f" {value}"
            print(
                f"dimenet train: warning: {flag}{shown} is ignored: --init {args.init} keeps its own {its[field]}",
                file=sys.stderr,
            )
    return {"features": f, "head": kept["head"]}


def _run_train(args: argparse.Namespace) -> int:
    from dimenet.runtime.rectify.model import resolve_model

    from .init_weights import initial_weights
    from .run_dir import CHECKPOINT, CURVE, HISTORY, SPEC, WEIGHTS
    from .trainer import read_training_data, train

    if args.resume is not None:
        return _resume(args)
    if args.data is None or args.out is None:
        raise CliError("dimenet train: give DATA --out RUN_DIR (a training), or --resume RUN_DIR (one that stopped)")
    checkpoint = Path(args.out) / CHECKPOINT
    if checkpoint.is_file():
        raise CliError(
            f"dimenet train: {checkpoint} is a training that stopped before its end: `dimenet train --resume "
            f"{args.out}` continues it; remove that file to start again"
        )
    bundled = args.init is None or resolve_model(args.init).bundled is not None
    init_files = [] if bundled else [Path(args.init) / name for name in ("", WEIGHTS, SPEC)]
    refuse_overwriting_inputs(
        "dimenet train",
        [("--out", Path(args.out) / name) for name in (WEIGHTS, SPEC, HISTORY, CURVE)],
        [("DATA", args.data), *(("--init", path) for path in init_files)],
    )
    datasets, sha256 = read_training_data(args.data)
    init = None if args.init is None else initial_weights(args.init)
    config = TrainConfig(
        **_network_settings(args, init),
        epochs=QUICK_EPOCHS if args.quick else args.epochs,
        seed=args.seed,
        focal_weight=args.focal_weight,
        train_frames=args.train_frames,
        k_c_error=args.k_c_error,
        plane_share=args.plane_share,
    )
    result = train(
        datasets,
        config,
        args.out,
        dataset_sha256=sha256,
        command="dimenet " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        init=init,
        origin={
            "data": str(Path(args.data).resolve()),
            "init": args.init if bundled else str(Path(args.init).resolve()),
        },
    )
    return _trained(result)


def _trained(result) -> int:
    print(
        f"trained {len(result.history)} epochs, kept epoch {result.best_epoch} "
        f"(best val Avg(e) {result.best_val_e:.3f} px), {result.seconds:.0f} s -> {result.run_dir}"
    )
    return 0


def _resume(args: argparse.Namespace) -> int:
    """`dimenet train --resume RUN_DIR`: the training of RUN_DIR's checkpoint, on from its last epoch."""
    from .init_weights import initial_weights
    from .run_dir import CHECKPOINT, HISTORY, WEIGHTS, read_checkpoint
    from .trainer import read_training_data, train

    parser = argparse.ArgumentParser()
    _add_train(parser)
    flags = {a.dest: a.option_strings[0] if a.option_strings else a.dest.upper() for a in parser._actions}
    alone = vars(parser.parse_args(["--resume", args.resume]))
    others = [flags[dest] for dest, value in alone.items() if getattr(args, dest) != value]
    if others:
        raise CliError(
            f"dimenet train --resume: {', '.join(others)} given, but a resumed training keeps the data, init and "
            "settings its checkpoint holds: give --resume RUN_DIR alone"
        )
    run = Path(args.resume)
    if not (run / CHECKPOINT).exists() and (run / WEIGHTS).is_file() and (run / HISTORY).is_file():
        print(f"{args.resume}: its training finished ({HISTORY} holds every epoch): nothing to resume")
        return 0
    _, state = read_checkpoint(args.resume)
    config = TrainConfig.from_dict(state["config"])
    origin = state["origin"]
    print(f"resuming {args.resume} after epoch {state['epoch']} of {config.epochs} ({state['command']})")
    datasets, sha256 = read_training_data(origin["data"])
    init = None if origin["init"] is None else initial_weights(origin["init"])
    result = train(
        datasets,
        config,
        args.resume,
        dataset_sha256=sha256,
        command=state["command"],
        init=init,
        origin=origin,
        resume=True,
    )
    return _trained(result)


TRAIN = Command(
    name="train",
    summary="Train DIME-Net on a dataset's train split (reprojection loss through the BPnP layer, plus a focal term).",
    example="dimenet train s8.npz --out runs/s8 --grid 8x6 --features A --seed 0\n"
    "  dimenet train family --out runs/generic --epochs 200   # a folder from `dimenet simulate --family`\n"
    "  dimenet train s8.npz --init default --train-frames 30 --out runs/s8-30   # fine-tune the default\n"
    "  dimenet train --resume runs/s8   # a training stopped (killed, a time limit): on from its last epoch",
    add_arguments=_add_train,
    run=_run_train,
)


def _add_reproduce(p: argparse.ArgumentParser) -> None:
    d = REPRODUCE_DEFAULTS
    p.add_argument(
        "--out",
        required=True,
        type=nonempty_path,
        metavar="DIR",
        help="folder for REPRODUCTION.md, results.json, plots, runs/",
    )
    p.add_argument(
        "--data-step",
        action="store_true",
        help="after the grid, give the network the frame's own Gauss-Newton step on K from the C0 pose and its "
        "posterior sigmas (not the paper's: an encoder that reads how the points fix K, whatever the scene)",
    )
    p.add_argument(
        "--epochs", type=epochs, default=d["epochs"], help=f"epochs of the three device models (default {d['epochs']})"
    )
    p.add_argument(
        "--ablation-epochs",
        type=epochs,
        default=d["ablation_epochs"],
        help=f"epochs of the Table 2/3 ablation models (default {d['ablation_epochs']})",
    )
    p.add_argument(
        "--seed",
        type=seed,
        default=d["seed"],
        help=f"seed of simulation, training and conditions (default {d['seed']})",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"a smoke run: {QUICK_EPOCHS} epoch per model, {QUICK_CAMERAS} cameras per held-out family (checks "
        "that the command runs end to end, in about 1 min on 2 cores; its numbers mean nothing, and the report "
        "says so)",
    )
    from dimenet.runtime.cli.arguments import add_address_argument

    add_address_argument(p, "trainings and evaluations")


def _run_reproduce(args: argparse.Namespace) -> int:
    from .reproduce import run

    quick = {"epochs": QUICK_EPOCHS, "ablation_epochs": QUICK_EPOCHS, "held_out_cameras": QUICK_CAMERAS}
    epochs = {"epochs": args.epochs, "ablation_epochs": args.ablation_epochs}
    results = run(
        ReproduceConfig(out_dir=Path(args.out), seed=args.seed, **(quick if args.quick else epochs)),
        address=args.address,
        cpus_per_job=args.cpus_per_job,
    )
    for name, r in results["table5"].items():
        rho = "-" if r["rho"] is None else f"{100 * r['rho']:.1f}%"
        print(
            f"{name:16s} Avg(e_c) {r['avg_e_c']:.2f}  Avg(e) {r['avg_e']:.2f}  Avg(e*) {r['avg_e_star']:.2f}  rho {rho}"
        )
    print(f"report: {Path(args.out) / 'REPRODUCTION.md'} ({results['seconds'] / 60:.1f} min)")
    return 0


REPRODUCE = Command(
    name="reproduce",
    summary="Regenerate the paper's Tables 2-5 on the simulated profiles and the generic default beside them "
    "(trains 9 models, fine-tunes one; 9-16 min on a 2-core VM, 5-9 with --address local:2; --quick: ~2 min).",
    example="dimenet reproduce --out reproduction",
    add_arguments=_add_reproduce,
    run=_run_reproduce,
)


def _add_fleet(p: argparse.ArgumentParser) -> None:
    from dimenet.runtime.cli.arguments import add_address_argument

    p.add_argument("action", choices=("train",), help="train: one `dimenet train` per job of the manifest")
    p.add_argument(
        "manifest", type=nonempty_path, help='a JSON manifest {"jobs": [{"name": ..., "dataset": ...}, ...]}'
    )
    p.add_argument(
        "--out", required=True, type=nonempty_path, metavar="DIR", help="folder of the run dirs and the summary"
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"a smoke run: {QUICK_EPOCHS} epoch per job, whatever the manifest says (checks that the jobs run end "
        "to end; the models learn nothing)",
    )
    add_address_argument(p, "jobs")


def _run_fleet(args: argparse.Namespace) -> int:
    from .fleet import SUMMARY_JSON, SUMMARY_MD, fleet_train

    outputs = [("--out", Path(args.out) / name) for name in (SUMMARY_JSON, SUMMARY_MD)]
    refuse_overwriting_inputs("dimenet fleet train", outputs, [("MANIFEST", args.manifest)])
    summary = fleet_train(
        args.manifest,
        args.out,
        address=args.address,
        cpus_per_job=args.cpus_per_job,
        epochs=QUICK_EPOCHS if args.quick else None,
    )
    print((Path(args.out) / SUMMARY_MD).read_text(encoding="utf-8"), end="")
    for name in summary["failed"]:
        print(f"failed: {name}", file=sys.stderr)
    return 1 if summary["failed"] else 0


FLEET = Command(
    name="fleet",
    summary="Train many models at once from a manifest (one `dimenet train` each), here or as Ray jobs.",
    example="dimenet fleet train devices.json --out fleet --address local:2",
    add_arguments=_add_fleet,
    run=_run_fleet,
)
