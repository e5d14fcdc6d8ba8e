"""`dimenet simulate`: write a simulated OIS dataset (rig frames, optionally natural-scene and planar frames,
lens distortion and the phone SDK's per-frame K), for one paper profile or, with ``--family N``, one dataset
per camera of a random camera family."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dimenet.runtime.cli.arguments import add_address_argument, finite_float_in, integer_in, nonempty_path, seed
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.dataset import Dataset, write_dataset
from dimenet.runtime.jobs.engine import run_all
from dimenet.runtime.sim.family import MAX_FAMILY, SCENES, family_member, family_profiles, hfov_deg
from dimenet.runtime.sim.mislabels import MAX_MISLABEL_SHARE, MISLABEL_PX
from dimenet.runtime.sim.profiles import PROFILES, DeviceProfile
from dimenet.runtime.sim.recording import KINDS as RECORDING_KINDS
from dimenet.runtime.sim.recording import simulate_recording, write_recording
from dimenet.runtime.sim.simulator import checked_dist_coeffs, simulate

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
    camera.add_argument(
        "--recording",
        choices=RECORDING_KINDS,
        help="a hand-held recording with a temporal OIS loop of a random natural scene or rig (models_spec/"
        "simulator.md, 'Recordings'): --out is a directory getting points.csv, gyro.csv, camera.json, truth.npz",
    )
    p.add_argument("--seconds", type=float, default=10.0, help="with --recording, its length (s, default 10)")
    p.add_argument("--cuts", type=integer_in(0, 100), default=1, help="with --recording, cuts in it (default 1)")
    p.add_argument(
        "--held-out",
        action="store_true",
        help="with --recording, draw the hand and OIS from the held-out trace model (training never draws from it)",
    )
    p.add_argument("--ois-off", action="store_true", help="with --recording, a camera without OIS")
    p.add_argument(
        "--scenes",
        choices=SCENES,
        default="paper",
        help="with --family, what each camera sees: the paper's rig (default), or a random rig of its own, 2-6 "
        "plain or ChArUco boards, framed from a fifth of the image to most of it, through the camera's residual "
        "lens, corner bias and JPEG noise (models_spec/simulator.md, 'Scene family')",
    )
    p.add_argument("--seed", type=seed, default=0, help="random seed (default 0); same seed, same file(s)")
    p.add_argument(
        "--natural-frames",
        type=integer_in(0, MAX_EXTRA_FRAMES),
        default=0,
        help="natural-scene test frames to add (the paper has 34; default 0), per camera: the paper's LEGO "
        "buildings, or with --scenes random a room, street or table of the camera's own",
    )
    p.add_argument(
        "--mislabels",
        type=finite_float_in(0.0, MAX_MISLABEL_SHARE),
        default=0.0,
        metavar="SHARE",
        help="with --natural-frames, this share of the natural labels clicked on the wrong feature, "
        f"{MISLABEL_PX[0]:g}-{MISLABEL_PX[1]:g} px off (models_spec/simulator.md, 'Mislabels'; default 0)",
    )
    p.add_argument(
        "--planar-frames",
        type=integer_in(0, MAX_EXTRA_FRAMES),
        default=0,
        help="planar test frames to add: rig photos whose K is inferred from one board only (default 0), per camera",
    )
    p.add_argument(
        "--dist-coeffs",
        type=dist_coeffs,
        metavar="K1,K2,P1,P2[,K3...]",
        help="lens distortion, OpenCV's 4/5/8/12/14 coefficients about the camera's nominal K (default: none): "
        "the points are as the distorted image holds them, per camera (a negative first one: --dist-coeffs=-0.1,...)",
    )
    p.add_argument(
        "--platform-k",
        action="store_true",
        help="add K_platform, the phone SDK's K per frame (simulated Hall-sensor readout of the lens; "
        "models_spec/simulator.md), per camera",
    )
    p.add_argument(
        "--out",
        required=True,
        type=nonempty_path,
        help="dataset file to write (dimenet-dataset/1 .npz); with --family a directory, one <camera>.npz each",
    )
    add_address_argument(p, "cameras of --family")


def dist_coeffs(text: str) -> tuple:
    """argparse type: comma-separated OpenCV distortion coefficients (4, 5, 8, 12 or 14 numbers)."""
    try:
        values = tuple(float(v) for v in text.split(","))
        return tuple(checked_dist_coeffs(values).tolist())
    except (ValueError, InputError) as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc}") from None


def frame_counts(ds: Dataset) -> str:
    """'R train + T test rig frames, N natural and P planar test frames' of a simulated dataset."""
    rig, test = ds.scene == "rig", ds.frames_in("test")
    return (
        f"{int(np.sum(rig & ds.frames_in('train')))} train + {int(np.sum(rig & test))} test rig frames, "
        f"{int(np.sum(ds.scene == 'natural'))} natural and {int(np.sum(ds.scene == 'planar'))} planar test frames"
    )


def extras(ds: Dataset) -> str:
    """', lens distortion k1,k2,...' and ', K_platform' when the dataset has them, else ''."""
    lens = "" if ds.dist_coeffs is None else ", lens distortion " + ",".join(f"{v:g}" for v in ds.dist_coeffs)
    return lens + ("" if ds.K_platform is None else ", K_platform")


def camera_summary(profile: DeviceProfile) -> str:
    """One camera of a family, in a few words: size, field of view, focal length, OIS, noise."""
    width_px, height_px = profile.image_size_px
    return (
        f"{width_px}x{height_px} px, hfov {hfov_deg(profile):.1f} deg, f {profile.focal_px:.0f} px, "
        f"shake {profile.shake_sigma_deg:.2f} / stroke {profile.ois_stroke_deg:.2f} deg, "
        f"corners {profile.corner_sigma_px:.2f} px"
    )


def write_member(job: tuple) -> tuple[str, int]:
    """One camera of a family to ``out``/<camera>.npz (a job of ``run_all``): job = (profile, index,
    seed, n, natural_frames, planar_frames, dist_coeffs, platform_k, scenes, mislabels, out). Returns its summary
    line and frame count."""
    profile, index, seed_, n, natural_frames, planar_frames, dist, platform_k, scenes, mislabels, out = job
    ds = family_member(
        profile,
        index,
        seed_,
        n,
        natural_frames=natural_frames,
        planar_frames=planar_frames,
        dist_coeffs=dist,
        platform_k=platform_k,
        scenes=scenes,
        mislabel_share=mislabels,
    )
    path = write_dataset(ds, Path(out) / f"{profile.name}.npz")
    boards = ds.meta["rig"]["boards"]
    rig = ""
    if scenes == "random":
        kind = "plain" if ds.meta["image_errors"]["charuco_missing"] is None else "ChArUco"
        rig = f", a rig of {len(boards)} {kind} boards of {boards[0]['square_mm']:.1f} mm squares"
    simulated = DeviceProfile(**ds.meta["device"])  # the camera as simulated: a random scene draws its OIS
    return f"{profile.name}: {camera_summary(simulated)}{rig}: {frame_counts(ds)}{extras(ds)} -> {path}", ds.n_frames


def run_family(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    profiles = family_profiles(args.family, args.seed)
    jobs = [
        (
            p,
            i,
            args.seed,
            args.family,
            args.natural_frames,
            args.planar_frames,
            args.dist_coeffs,
            args.platform_k,
            args.scenes,
            args.mislabels,
            str(out),
        )
        for i, p in enumerate(profiles)
    ]
    outcomes = run_all(write_member, jobs, address=args.address, cpus_per_job=args.cpus_per_job, desc="simulate")
    for outcome, profile in zip(outcomes, profiles):
        if outcome.error is not None:
            raise CliError(f"{profile.name}: {outcome.error}")
        print(outcome.value[0], flush=True)
    frames = sum(o.value[1] for o in outcomes)
    print(f"family seed {args.seed}: {args.family} cameras, {frames} frames in all -> {out}")
    return 0


def run_recording(args: argparse.Namespace) -> int:
    try:
        recording = simulate_recording(
            args.seed,
            seconds=args.seconds,
            kind=args.recording,
            held_out=args.held_out,
            ois=not args.ois_off,
            cuts=args.cuts,
        )
    except InputError as exc:
        raise CliError(f"dimenet simulate --recording: {exc}") from None
    paths = write_recording(recording, args.out)
    ds = recording.dataset
    trace = ds.meta["recording"]["trace"]
    print(
        f"recording seed {args.seed}: {ds.n_frames} frames at {trace['fps']:g} fps, {args.recording} scene, "
        f"cuts at {list(recording.cuts)}, refocus at {list(recording.refocus)}, gyro {len(recording.gyro)} samples "
        f"-> {', '.join(str(p) for p in paths.values())}"
    )
    return 0


def run(args: argparse.Namespace) -> int:
    if args.recording is not None:
        return run_recording(args)
    if args.family is not None:
        return run_family(args)
    if args.scenes != "paper":
        raise CliError("dimenet simulate: --scenes random needs --family (a paper profile sees the paper's rig)")
    ds = simulate(
        args.profile,
        seed=args.seed,
        natural_frames=args.natural_frames,
        planar_frames=args.planar_frames,
        dist_coeffs=args.dist_coeffs,
        platform_k=args.platform_k,
        mislabel_share=args.mislabels,
    )
    path = write_dataset(ds, args.out)
    print(
        f"{args.profile} seed {args.seed}: {frame_counts(ds)}, "
        f"{ds.n_points} points per frame ({int(ds.valid.sum())} valid in all){extras(ds)} -> {path}"
    )
    return 0


COMMAND = Command(
    name="simulate",
    summary="Simulate an OIS phone photographing the paper's 4-board rig (and, optionally, the LEGO scene); "
    "--family: many random cameras, one dataset each.",
    example="dimenet simulate --profile galaxy-s8 --seed 0 --natural-frames 34 --planar-frames 40 --out s8.npz\n"
    "  dimenet simulate --profile galaxy-s8 --platform-k --dist-coeffs 0.08,-0.15,0,0 --out s8-sdk.npz\n"
    "  dimenet simulate --family 100 --seed 0 --natural-frames 10 --out family\n"
    "  dimenet simulate --family 100 --seed 0 --scenes random --out family-scenes\n"
    "  dimenet simulate --family 100 --seed 0 --out family --address local:2   # the fleet extra: Ray jobs\n"
    "  dimenet simulate --recording natural --seed 3 --seconds 10 --held-out --out rec   # a hand-held video",
    add_arguments=add_arguments,
    run=run,
)
