"""`dimenet samples --out DIR`: the inputs the README's and the --help's examples read that no other command
makes, written from the bundled files: ``frames.npz`` (the example frames of `dimenet rectify --example`),
``cam.json`` (their camera, a camera file), ``rec.csv`` (the same frames as an app's recording,
models_spec/points-csv.md), and ``real-photos/<set>/rig.json``, the rig of each real-photo set, beside which
go the set's photos (README.md, "Real photos"). Each file is written atomically; one line per file says
what it is for."""

from __future__ import annotations

import argparse
from importlib import resources
from pathlib import Path

from dimenet.runtime.assets import asset
from dimenet.runtime.bench.real_suite import RIG_ASSETS, RIG_FILE
from dimenet.runtime.bench.streaming import points_csv
from dimenet.runtime.cli.arguments import nonempty_path
from dimenet.runtime.cli.commands.rectify import EXAMPLE_CAMERA, EXAMPLE_DATA
from dimenet.runtime.cli.main import Command
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.dataset import read_dataset

FRAMES, CAMERA, RECORDING, REAL_PHOTOS = "frames.npz", "cam.json", "rec.csv", "real-photos"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--out",
        required=True,
        type=nonempty_path,
        metavar="DIR",
        help=f"folder for {FRAMES}, {CAMERA}, {RECORDING} and {REAL_PHOTOS}/<set>/{RIG_FILE} (created; the files "
        "are replaced)",
    )


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    written = []

    def copy(name: str, target: Path, what: str) -> None:
        data = asset(name).read_bytes()
        written.append((atomic_write(target, lambda f: f.write(data)), what))

    copy(EXAMPLE_DATA, out / FRAMES, "8 simulated galaxy-s8 frames (a dataset: `dimenet rectify FILE`)")
    copy(EXAMPLE_CAMERA, out / CAMERA, "their camera, K_c and image size (a camera file: --camera FILE)")
    with resources.as_file(asset(EXAMPLE_DATA)) as path:
        frames = read_dataset(path)
    lines = points_csv(frames, frames.n_frames)
    recording = atomic_write(out / RECORDING, lambda f: f.writelines(line.encode("utf-8") for line in lines))
    written.append((recording, "the same frames as an app's recording (`dimenet rectify --points FILE`)"))
    for folder, name in RIG_ASSETS.items():
        copy(
            name, out / REAL_PHOTOS / folder / RIG_FILE, f"the rig of the real-photo set {folder}: its photos go beside"
        )
    for path, what in written:
        print(f"{path}: {what}")
    return 0


COMMAND = Command(
    name="samples",
    summary="Write the sample inputs the README's and the help's examples read (example frames, their camera, an "
    "app's recording, the real-photo sets' rigs).",
    example="dimenet samples --out .   # frames.npz, cam.json, rec.csv, real-photos/*/rig.json",
    add_arguments=add_arguments,
    run=run,
)
