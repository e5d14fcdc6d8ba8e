"""`dimenet simulate`: write a simulated OIS dataset (rig frames, optionally natural-scene and planar frames)."""

from __future__ import annotations

import argparse

import numpy as np

from dimenet.runtime.cli.main import Command, integer_in, nonempty_path, seed
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.sim.simulator import PROFILES, simulate

MAX_EXTRA_FRAMES = 10_000  # natural or planar frames: ~13 KB and ~4 ms each (2**40: MemoryError)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--profile", required=True, choices=sorted(PROFILES), help="simulated device")
    p.add_argument("--seed", type=seed, default=0, help="random seed (default 0); same seed, same file")
    p.add_argument(
        "--natural-frames",
        type=integer_in(0, MAX_EXTRA_FRAMES),
        default=0,
        help="natural-scene (LEGO buildings) test frames to add (the paper has 34; default 0)",
    )
    p.add_argument(
        "--planar-frames",
        type=integer_in(0, MAX_EXTRA_FRAMES),
        default=0,
        help="planar test frames to add: rig photos whose K is inferred from one board only (default 0)",
    )
    p.add_argument("--out", required=True, type=nonempty_path, help="dataset file to write (dimenet-dataset/1 .npz)")


def run(args: argparse.Namespace) -> int:
    ds = simulate(args.profile, seed=args.seed, natural_frames=args.natural_frames, planar_frames=args.planar_frames)
    path = write_dataset(ds, args.out)
    rig, test = ds.scene == "rig", ds.frames_in("test")
    print(
        f"{args.profile} seed {args.seed}: {int(np.sum(rig & ds.frames_in('train')))} train + "
        f"{int(np.sum(rig & test))} test rig frames, {int(np.sum(ds.scene == 'natural'))} natural and "
        f"{int(np.sum(ds.scene == 'planar'))} planar test frames, "
        f"{ds.n_points} points per frame ({int(ds.valid.sum())} valid in all) -> {path}"
    )
    return 0


COMMAND = Command(
    name="simulate",
    summary="Simulate an OIS phone photographing the paper's 4-board rig (and, optionally, the LEGO scene).",
    example="dimenet simulate --profile galaxy-s8 --seed 0 --natural-frames 34 --planar-frames 40 --out s8.npz",
    add_arguments=add_arguments,
    run=run,
)
