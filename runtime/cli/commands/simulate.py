"""`dimenet simulate`: write a simulated OIS dataset (rig frames, optionally natural-scene and planar frames),
for one paper profile or, with ``--family N``, one dataset per camera of a random camera family."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dimenet.runtime.cli.main import Command, integer_in, nonempty_path, seed
from dimenet.runtime.formats.dataset import Dataset, write_dataset
from dimenet.runtime.sim.family import MAX_FAMILY, hfov_deg, simulate_family
from dimenet.runtime.sim.simulator import PROFILES, DeviceProfile, simulate

MAX_EXTRA_FRAMES = 10_000  # natural or planar frames: ~13 KB and ~4 ms each (2**40: MemoryError)


def add_arguments(p: argparse.ArgumentParser) -> None:
    camera = p.add_mutually_exclusive_group(required=True)
    camera.add_argument("--profile", choices=sorted(PROFILES), help="simulated device (one of the paper's)")
    camera.add_argument(
        "--family",
        type=integer_in(1, MAX_FAMILY),
        metavar="N",
        help=f"simulate N random cameras (1 to {MAX_FAMILY}; see models_spec/simulator.md, 'Camera family'), "
        "one dataset each in the --out directory",
    )
    p.add_argument("--seed", type=seed, default=0, help="random seed (default 0); same seed, same file(s)")
    p.add_argument(
        "--natural-frames",
        type=integer_in(0, MAX_EXTRA_FRAMES),
        default=0,
        help="natural-scene (LEGO buildings) test frames to add (the paper has 34; default 0), per camera",
    )
    p.add_argument(
        "--planar-frames",
        type=integer_in(0, MAX_EXTRA_FRAMES),
        default=0,
        help="planar test frames to add: rig photos whose K is inferred from one board only (default 0), per camera",
    )
    p.add_argument(
        "--out",
        required=True,
        type=nonempty_path,
        help="dataset file to write (dimenet-dataset/1 .npz); with --family a directory, one <camera>.npz each",
    )


def frame_counts(ds: Dataset) -> str:
    """'R train + T test rig frames, N natural and P planar test frames' of a simulated dataset."""
    rig, test = ds.scene == "rig", ds.frames_in("test")
    return (
        f"{int(np.sum(rig & ds.frames_in('train')))} train + {int(np.sum(rig & test))} test rig frames, "
        f"{int(np.sum(ds.scene == 'natural'))} natural and {int(np.sum(ds.scene == 'planar'))} planar test frames"
    )


def camera_summary(profile: DeviceProfile) -> str:
    """One camera of a family, in a few words: size, field of view, focal length, OIS, noise."""
    width_px, height_px = profile.image_size_px
    return (
        f"{width_px}x{height_px} px, hfov {hfov_deg(profile):.1f} deg, f {profile.focal_px:.0f} px, "
        f"shake {profile.shake_sigma_deg:.2f} / stroke {profile.ois_stroke_deg:.2f} deg, "
        f"corners {profile.corner_sigma_px:.2f} px"
    )


def run_family(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    frames = 0
    extra = {"natural_frames": args.natural_frames, "planar_frames": args.planar_frames}
    family = simulate_family(args.family, args.seed, **extra)
    for profile, ds in family:
        path = write_dataset(ds, out / f"{profile.name}.npz")
        frames += ds.n_frames
        print(f"{profile.name}: {camera_summary(profile)}: {frame_counts(ds)} -> {path}", flush=True)
    print(f"family seed {args.seed}: {args.family} cameras, {frames} frames in all -> {out}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.family is not None:
        return run_family(args)
    ds = simulate(args.profile, seed=args.seed, natural_frames=args.natural_frames, planar_frames=args.planar_frames)
    path = write_dataset(ds, args.out)
    print(
        f"{args.profile} seed {args.seed}: {frame_counts(ds)}, "
        f"{ds.n_points} points per frame ({int(ds.valid.sum())} valid in all) -> {path}"
    )
    return 0


COMMAND = Command(
    name="simulate",
    summary="Simulate an OIS phone photographing the paper's 4-board rig (and, optionally, the LEGO scene); "
    "--family: many random cameras, one dataset each.",
    example="dimenet simulate --profile galaxy-s8 --seed 0 --natural-frames 34 --planar-frames 40 --out s8.npz\n"
    "  dimenet simulate --family 100 --seed 0 --natural-frames 10 --out family",
    add_arguments=add_arguments,
    run=run,
)
