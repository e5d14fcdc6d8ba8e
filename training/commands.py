"""`dimenet train` (and the other torch-side subcommands). Torch is imported only when run."""
from __future__ import annotations

import argparse
import shlex
import sys

from dimenet.runtime.cli import Command



def _add_train(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", help="dataset file (dimenet-dataset/1 .npz) with a train split")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="folder for weights, spec.json, curve.png")
    p.add_argument("--grid", default="8x6", help="grid, columns x rows (default 8x6)")
    p.add_argument("--features", default="A", choices="ABCDE", help="feature variant of paper Table 3 (default A)")
    p.add_argument("--epochs", type=int, default=400, help="maximum epochs (default 400; early stopping on val)")
    p.add_argument("--seed", type=int, default=0, help="seed: same seed, same model (default 0)")


def _run_train(args: argparse.Namespace) -> int:
    from dimenet.runtime.dataset import read_dataset
    from dimenet.runtime.errors import InputError

    from .trainer import TrainConfig, file_sha256, train

    if args.epochs < 1:
        raise InputError(f"--epochs must be >= 1, got {args.epochs}")
    ds = read_dataset(args.data)
    config = TrainConfig(grid=args.grid, variant=args.features, epochs=args.epochs, seed=args.seed)
    result = train(ds, config, args.out, dataset_sha256=file_sha256(args.data),
                   command="dimenet " + " ".join(shlex.quote(a) for a in sys.argv[1:]))
    print(f"trained {result.best_epoch} epochs (best), val Avg(e) {result.best_val_e:.3f} px, "
          f"{result.seconds:.0f} s -> {result.run_dir}")
    return 0


TRAIN = Command(
    name="train",
    summary="Train DIME-Net on a dataset's train split (reprojection loss through the BPnP layer).",
    example="dimenet train s8.npz --out runs/s8 --grid 8x6 --features A --seed 0",
    add_arguments=_add_train,
    run=_run_train,
)
