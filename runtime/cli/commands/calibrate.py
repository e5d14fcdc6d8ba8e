"""`dimenet calibrate`: per-frame K*, pose and e*, and the prior K_c from the train frames."""

from __future__ import annotations

import argparse
from typing import Optional

import numpy as np

from dimenet.runtime.cli.arguments import nonempty_path
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs
from dimenet.runtime.evaluation.calibration import calibrate_dataset, write_calibration
from dimenet.runtime.evaluation.multiview import DISTORTION_MODELS
from dimenet.runtime.formats.camera_file import FORMATS, SUFFIX_FORMATS, format_for_suffix, write_camera
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.geometry import k_params
from dimenet.runtime.rectify.user_camera import checked_camera


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", help="dataset file (dimenet-dataset/1 .npz)")
    p.add_argument(
        "--out",
        required=True,
        type=nonempty_path,
        help="calibration file to write (.npz: K_c, K_star, rvec, tvec, e_star)",
    )
    p.add_argument(
        "--camera-out",
        type=nonempty_path,
        metavar="FILE",
        help="also write K_c, the image size and the lens (if calibrated) as a camera file, for --camera "
        "(models_spec/camera-files.md)",
    )
    p.add_argument(
        "--distortion",
        choices=tuple(DISTORTION_MODELS),
        default="none",
        help="fit one lens distortion over the train frames (opencv4: k1, k2, p1, p2; opencv5: + k3; opencv8: "
        "rational) with each frame's own K and pose (rig views; OIS moves K, the lens stays), or with one K "
        "(single-board views), then each frame's K* on the undistorted points (default none: the dataset's own "
        "lens, if it carries one)",
    )
    suffixes = ", ".join(f"{suffix} {fmt}" for suffix, fmt in SUFFIX_FORMATS.items())
    p.add_argument(
        "--camera-format",
        choices=FORMATS,
        help=f"the camera file's format (default from its suffix: {suffixes}; a .yaml needs it)",
    )


def _camera_format(args: argparse.Namespace) -> Optional[str]:
    """The format of --camera-out (None: no camera file), checked before the calibration runs."""
    if args.camera_out is None:
        if args.camera_format is not None:
            raise CliError("dimenet calibrate: --camera-format needs --camera-out FILE")
        return None
    fmt = args.camera_format or format_for_suffix(args.camera_out)
    if fmt is None:
        raise CliError(
            f"dimenet calibrate: --camera-out {args.camera_out}: its suffix names no format, "
            f"give --camera-format ({', '.join(FORMATS)})"
        )
    return fmt


def run(args: argparse.Namespace) -> int:
    outputs = [("--out", args.out)] + ([] if args.camera_out is None else [("--camera-out", args.camera_out)])
    refuse_overwriting_inputs("dimenet calibrate", outputs, [("DATA", args.data)])
    camera_format = _camera_format(args)
    ds = read_dataset(args.data)
    cal = calibrate_dataset(ds, args.distortion)
    write_calibration(cal, args.out)
    if camera_format is not None:
        size = tuple(int(v) for v in ds.image_size)
        # Every camera format states the lens about the file's own K: with a lens, that is its K.
        K = cal.K_c if cal.dist_K is None else cal.dist_K
        camera = checked_camera(K, size, "K_c", cal.dist_coeffs)
        write_camera(args.camera_out, camera, camera_format)
        print(f"camera (K_c, {camera.image_size[0]}x{camera.image_size[1]} px) -> {args.camera_out} ({camera_format})")
    fx, fy, cx, cy = k_params(cal.K_c)
    for b in cal.outliers:
        name = ds.frame_id[b] if ds.frame_id is not None else f"frame {b}"
        print(f"left out of K_c: {name} (K* {k_params(cal.K_star[b]).round(1).tolist()} px, e* {cal.e_star[b]:.3g} px)")
    n_train = int(ds.frames_in("train").sum())
    source = (
        f"{n_train - len(cal.outliers)} train frames"
        if cal.K_c_from == "mean K*"
        else f"the joint fit of {n_train} train frames"
    )
    observed = np.isfinite(cal.e_star)
    print(
        f"K_c from {source}: fx={fx:.2f} fy={fy:.2f} cx={cx:.2f} cy={cy:.2f} px; "
        + (
            f"mean e* over {int(observed.sum())} frames {cal.e_star[observed].mean():.3f} px"
            if observed.any()
            else "no frame gives K*"
        )
        + f" -> {args.out}"
    )
    unobservable = [r for r in cal.reasons if r is not None]
    if unobservable:
        print(f"{len(unobservable)} frame(s) give no K* (NaN in the file): {unobservable[0]}")
    if cal.dist_coeffs is not None:
        whose = f"fitted, {args.distortion}" if args.distortion != "none" else "the dataset's"
        print(f"lens ({whose}): dist_coeffs {np.round(cal.dist_coeffs, 6).tolist()}")
    return 0


COMMAND = Command(
    name="calibrate",
    summary="Calibrate every frame (K* and pose by joint LM, e*) and the prior K_c (mean K* of the train frames).",
    example="dimenet calibrate s8.npz --out s8-cal.npz --camera-out s8-camera.yaml --camera-format opencv-yaml",
    add_arguments=add_arguments,
    run=run,
)
