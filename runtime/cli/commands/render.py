"""`dimenet render`: photos of the rig through the simulator's OIS camera, with their truth (for testing ingest)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dimenet.runtime.cli.arguments import finite_float_in, integer_in, nonempty_path, seed
from dimenet.runtime.cli.commands.simulate import dist_coeffs
from dimenet.runtime.cli.main import Command
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs
from dimenet.runtime.formats.rig import PAPER_RIG_NAME, rig_from_argument
from dimenet.runtime.jobs.progress import progress
from dimenet.runtime.sim.profiles import PROFILES, get_profile
from dimenet.runtime.sim.render import FORMATS, TRUTH_FILE, photo_name, scaled_profile, write_render

MAX_PHOTOS = 10_000  # --n here and in `dimenet bench --ingest`: ~30 GB of full-size JPEGs
MAX_SCALE = 64.0  # 4032x3024 -> 63x47 px; past that the boards are a few pixels


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", required=True, help="rig file (dimenet-rig/1 JSON), or `paper` for the bundled paper rig")
    p.add_argument("--profile", required=True, choices=sorted(PROFILES), help="simulated device")
    p.add_argument("--n", type=integer_in(1, MAX_PHOTOS), required=True, help="number of photos")
    p.add_argument(
        "--out", required=True, type=nonempty_path, help=f"folder for photo-0000.<format>, ... and {TRUTH_FILE}"
    )
    p.add_argument("--seed", type=seed, default=0, help="random seed (default 0); same seed, same photos")
    p.add_argument("--format", choices=FORMATS, default="jpg", help="photo format (default jpg)")
    p.add_argument(
        "--scale",
        type=finite_float_in(1.0, MAX_SCALE),
        default=1.0,
        help=f"render this many times fewer pixels per side, same field of view, 1 to {MAX_SCALE:g} "
        "(default 1: full size)",
    )
    p.add_argument(
        "--dist-coeffs",
        type=dist_coeffs,
        metavar="K1,K2,P1,P2[,K3...]",
        help="take the photos through a lens: OpenCV's 4/5/8/12/14 coefficients about the profile's nominal K "
        "(default: none); truth.npz then holds the distorted corners and the lens (a negative first one: "
        "--dist-coeffs=-0.1,...)",
    )


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    outputs = [("--out", out / photo_name(k, args.format)) for k in range(args.n)] + [("--out", out / TRUTH_FILE)]
    refuse_overwriting_inputs("dimenet render", outputs, [] if args.rig == PAPER_RIG_NAME else [("--rig", args.rig)])
    profile = scaled_profile(get_profile(args.profile), args.scale)
    rig = rig_from_argument(args.rig)
    truth = write_render(
        args.out,
        rig,
        profile,
        args.n,
        seed=args.seed,
        fmt=args.format,
        progress=lambda items: progress(items, total=args.n, desc="render"),
        dist_coeffs=None if args.dist_coeffs is None else np.array(args.dist_coeffs),
    )
    w, h = profile.image_size_px
    covered = ", every 5th from the 4th with a board covered" if len(rig.boards) >= 3 else ""
    lens = "" if args.dist_coeffs is None else ", through the lens"
    print(
        f"{args.n} photos of {w}x{h} px ({args.profile}, seed {args.seed}{lens}; every 5th from the 2nd upside "
        f"down{covered}) -> {args.out} (truth: {truth})"
    )
    return 0


COMMAND = Command(
    name="render",
    summary="Render photos of a rig through the simulator's OIS camera (clutter, blur, noise, vignetting), "
    "with the true corners and K per photo, to test `dimenet ingest` end to end.",
    example="dimenet render --rig paper --profile galaxy-s8 --n 30 --out shots\n"
    "  dimenet render --rig paper --profile galaxy-s8 --n 30 --scale 3 --dist-coeffs=-0.11,0.06,0,0 --out lens-shots",
    add_arguments=add_arguments,
    run=run,
)
