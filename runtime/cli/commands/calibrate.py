"""`dimenet calibrate`: per-frame K*, pose and e*, and the prior K_c from the train frames."""

from __future__ import annotations

import argparse

from dimenet.runtime.cli.main import Command, nonempty_path
from dimenet.runtime.evaluation.calibration import calibrate_dataset, write_calibration
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.geometry import k_params


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", help="dataset file (dimenet-dataset/1 .npz)")
    p.add_argument(
        "--out",
        required=True,
        type=nonempty_path,
        help="calibration file to write (.npz: K_c, K_star, rvec, tvec, e_star)",
    )


def run(args: argparse.Namespace) -> int:
    ds = read_dataset(args.data)
    cal = calibrate_dataset(ds)
    write_calibration(cal, args.out)
    fx, fy, cx, cy = k_params(cal.K_c)
    for b in cal.outliers:
        name = ds.frame_id[b] if ds.frame_id is not None else f"frame {b}"
        print(f"left out of K_c: {name} (K* {k_params(cal.K_star[b]).round(1).tolist()} px, e* {cal.e_star[b]:.3g} px)")
    print(
        f"K_c from {int(ds.frames_in('train').sum()) - len(cal.outliers)} train frames: "
        f"fx={fx:.2f} fy={fy:.2f} cx={cx:.2f} cy={cy:.2f} px; "
        f"mean e* over {ds.n_frames} frames {cal.e_star.mean():.3f} px -> {args.out}"
    )
    return 0


COMMAND = Command(
    name="calibrate",
    summary="Calibrate every frame (K* and pose by joint LM, e*) and the prior K_c (mean K* of the train frames).",
    example="dimenet calibrate s8.npz --out s8-cal.npz",
    add_arguments=add_arguments,
    run=run,
)
