"""`dimenet rectify`: per-frame K and pose of every frame of a dataset (or of the bundled example),
or of an app's recording of correspondences streamed frame by frame (``--points FILE``).

Dataset: each frame's K is inferred from its ``infer_mask`` points (what the model may see, as
in evaluation); its pose and errors use all its valid points under K and under K_c. Points file
(``formats.points``, models_spec/points-csv.md): read one frame at a time, each frame through
``Rectifier.rectify`` (all its points), one JSON line per frame to stdout or ``--out FILE.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import Counter
from collections.abc import Iterable, Iterator
from importlib import resources

import numpy as np

from dimenet.runtime.assets import asset
from dimenet.runtime.cli.arguments import finite_float_in, nonempty_path
from dimenet.runtime.cli.camera_option import add_camera_argument, require_dataset_size, served_camera
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs
from dimenet.runtime.evaluation.rectify_points import rectified_records, streamed_records
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.camera_file import camera_file, read_camera
from dimenet.runtime.formats.dataset import Dataset, read_dataset
from dimenet.runtime.formats.motion import GYRO, read_motion
from dimenet.runtime.formats.points import PointsFrame, read_points
from dimenet.runtime.formats.rectified_points import counted, json_lines, run_record
from dimenet.runtime.geometry import k_params
from dimenet.runtime.jobs.progress import progress
from dimenet.runtime.rectify.gyro_ois import MAX_SCALE
from dimenet.runtime.rectify.model import BUNDLED_HELP, load_model
from dimenet.runtime.rectify.rectifier import MODES, Rectifier
from dimenet.runtime.rectify.results import BatchRectification

EXAMPLE_DATA = "example_frames.npz"
EXAMPLE_CAMERA = "example_camera.json"  # the example's camera (galaxy-s8 K_c calibrated on its train split)
PROGRESS_BLOCK = 1 << 20  # the points bar counts MiB of the file read


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="?", help="dataset file (dimenet-dataset/1 .npz)")
    p.add_argument(
        "--points",
        type=nonempty_path,
        metavar="FILE",
        help="instead of a dataset: a CSV or JSON Lines file of 2D-3D points, frame by frame "
        "(models_spec/points-csv.md), streamed; one JSON line per frame to stdout (or --out FILE.jsonl); the camera "
        "from --camera FILE (a generic model, as the bundled one, needs it; a device model defaults to its own)",
    )
    p.add_argument(
        "--example",
        action="store_true",
        help=f"rectify the bundled sample ({EXAMPLE_DATA}: 8 simulated galaxy-s8 frames)",
    )
    p.add_argument(
        "--model",
        type=nonempty_path,
        help=f"a .onnx from `dimenet export`, or a bundled model: {BUNDLED_HELP}",
    )
    add_camera_argument(p)
    p.add_argument(
        "--mode",
        choices=MODES,
        default="dimenet",
        help="dimenet (default): the network's K; map: the network's K as a prior fused with the frame's "
        "points (needs a model with an uncertainty model, spec >= 1.1)",
    )
    p.add_argument(
        "--out",
        type=nonempty_path,
        metavar="RESULT.npz",
        help="write K, rvec, tvec, e, e_c, delta_k, fallback, fallback_code and (with an uncertainty model) K_cov "
        "per frame, and K_c, image_size, model_sha256; with --points: FILE.jsonl, the JSON lines",
    )
    p.add_argument("--refine", action="store_true", help="polish poses with cv2.solvePnPRefineLM (e as in evaluate)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.add_argument(
        "--temporal",
        action="store_true",
        help="with --points: track K through the recording (rectify.stream: each frame's K fused with the frames "
        "before, reset at cuts, refocus and gaps in t_ns); each line adds event and fused",
    )
    p.add_argument(
        "--motion",
        type=nonempty_path,
        metavar="MOTION.csv",
        help="with --temporal: the gyroscope's samples, t_ns,gx_rad_s,gy_rad_s,gz_rad_s in the camera's axes (c "
        "predicted from the rotation through the OIS loop), or the platform's lens-shift samples, "
        "t_ns,x_shift_px,y_shift_px (Android's STATISTICS_OIS_SAMPLES: c follows the shift), on the points' clock "
        "(models_spec/points-csv.md, 'Motion')",
    )
    p.add_argument(
        "--ois-scale",
        type=finite_float_in(0.0, MAX_SCALE, above=True),
        default=None,
        metavar="S",
        help="with a lens-shift --motion: the stream's px per px of the sensor's active array, which the shifts are "
        "in (default 1: the stream is the active array; e.g. 1920 / 4032 for a 1080p stream of a 4032 px array)",
    )


def result_arrays(frames: Dataset, res: BatchRectification, rectifier: Rectifier) -> dict:
    """The RESULT.npz arrays (plain dtypes, no pickle): fallback and fallback_code (``FALLBACK_CODES``)
    '' where there is none; K_cov
    (F, 4, 4) px^2, NaN where K is K_c's, only when the model has an uncertainty model; which
    camera and model produced them: K_c (3, 3) px, image_size (2,) px (width, height),
    model_sha256 (a str array of shape ())."""
    frame_id = frames.frame_id if frames.frame_id is not None else np.arange(frames.n_frames).astype(str)
    arrays = {
        "frame_id": np.asarray(frame_id),
        "K": res.K,
        "rvec": res.rvec,
        "tvec": res.tvec,
        "e": res.reprojection_error_px,
        "e_c": res.reprojection_error_kc_px,
        "delta_k": res.delta_k,
        "fallback": np.array([r or "" for r in res.fallback]),
        "fallback_code": np.array([c or "" for c in res.fallback_code]),
        "K_c": rectifier.K_c,
        "image_size": np.array(rectifier.image_size, dtype=np.int64),
        "model_sha256": np.array(rectifier.model.sha256),
    }
    if res.K_cov is not None:
        arrays["K_cov"] = res.K_cov
    return arrays


def _k_sigma(arrays: dict, i: int) -> list | None:
    """Frame i's standard deviations of (fx, fy, cx, cy) px, or None (no uncertainty model, or K_c)."""
    if "K_cov" not in arrays or not np.all(np.isfinite(arrays["K_cov"][i])):
        return None
    return np.sqrt(np.diag(arrays["K_cov"][i])).tolist()


def _summary(arrays: dict) -> dict:
    avg_e_c, avg_e = float(arrays["e_c"].mean()), float(arrays["e"].mean())
    return {
        "n_frames": len(arrays["e"]),
        "avg_e_c_px": avg_e_c,
        "avg_e_px": avg_e,
        "fallbacks": int((arrays["fallback"] != "").sum()),
    }


def _table(frames: Dataset, arrays: dict, source: str) -> str:
    rows = [("frame", "scene", "points", "e_c (px)", "e (px)", "fx", "fy", "cx", "cy", "fallback")]
    for i, fid in enumerate(arrays["frame_id"]):
        rows.append(
            (
                str(fid),
                str(frames.scene[i]),
                str(int(frames.valid[i].sum())),
                f"{arrays['e_c'][i]:.3f}",
                f"{arrays['e'][i]:.3f}",
                *(f"{v:.1f}" for v in k_params(arrays["K"][i])),
                arrays["fallback"][i] or "-",
            )
        )
    widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]) - 1)]
    lines = [
        "  ".join([c.ljust(w) if j < 2 else c.rjust(w) for j, (c, w) in enumerate(zip(r, widths))] + [r[-1]])
        for r in rows
    ]
    s = _summary(arrays)
    change = 100.0 * (s["avg_e_px"] - s["avg_e_c_px"]) / s["avg_e_c_px"]
    lines.append(
        f"{s['n_frames']} frames: Avg(e_c) {s['avg_e_c_px']:.3f} px -> Avg(e) {s['avg_e_px']:.3f} px "
        f"({change:+.1f} %), {s['fallbacks']} fallbacks; model {source}"
    )
    return "\n".join(lines)


def _frames(args: argparse.Namespace) -> Dataset:
    if args.example == bool(args.data):
        raise CliError("dimenet rectify: give a dataset file or --example (one of them)")
    if args.data:
        return read_dataset(args.data)
    with resources.as_file(asset(EXAMPLE_DATA)) as path:
        return read_dataset(path)


def _rectifier(args: argparse.Namespace, frames: Dataset) -> Rectifier:
    """The model serving the dataset's camera (``cli.camera_option.served_camera``; the bundled example's
    own camera file with --example)."""
    model = load_model(args.model)
    camera_file = args.camera
    if args.example and camera_file is None:
        with resources.as_file(asset(EXAMPLE_CAMERA)) as path:
            camera = read_camera(path)
    else:
        camera = served_camera(model.spec, frames, camera_file, model.source)
    rectifier = Rectifier(model, args.mode, camera)
    require_dataset_size(rectifier.image_size, frames, args.camera or model.source)
    return rectifier


def _points_rectifier(args: argparse.Namespace) -> Rectifier:
    """The model serving the camera file (None: a device model's own camera; a generic model
    without one is a CameraError saying so)."""
    camera = None if args.camera is None else read_camera(args.camera)
    return Rectifier(load_model(args.model), args.mode, camera)


def _blocks(frames: Iterable[PointsFrame]) -> Iterator[list[PointsFrame]]:
    """The frames in lists, one list per PROGRESS_BLOCK bytes of the file read (the rest with the
    last): a frame is held until its block is complete, so the bar counts bytes."""
    held, done = [], 0
    for frame in frames:
        held.append(frame)
        while done < frame.bytes_read // PROGRESS_BLOCK:
            yield held
            held, done = [], done + 1
    yield held


def _with_progress(frames: Iterable[PointsFrame], path: str) -> Iterator[PointsFrame]:
    """The frames, with a bar of MiB read against the file's size on a terminal's stderr."""
    try:
        size = os.stat(path).st_size
    except OSError:  # read_points names the problem
        size = 0
    total = size // PROGRESS_BLOCK + 1 if size else None  # a pipe or FIFO has no size
    for block in progress(_blocks(frames), total=total, desc="rectify, MiB read"):
        yield from block


def _run_points(args: argparse.Namespace) -> int:
    if args.example or args.data:
        raise CliError("dimenet rectify: give a dataset file, --example or --points FILE (one of them)")
    if args.json:
        raise CliError("dimenet rectify: --json applies to a dataset; --points always writes JSON lines")
    if args.temporal and args.mode != "dimenet":
        raise CliError("dimenet rectify: --temporal fuses the network's K over frames: it needs --mode dimenet")
    rectifier = _points_rectifier(args)
    header = run_record(rectifier, refine=args.refine, points=args.points, camera=args.camera)
    frames = _with_progress(read_points(args.points), args.points)
    tally: Counter = Counter()
    if args.temporal:
        header["temporal"] = True
        header["motion"] = args.motion
        records = streamed_records(rectifier.stream(refine=args.refine, **_motion_options(args)), frames)
    else:
        records = rectified_records(rectifier, frames, refine=args.refine)
    lines = json_lines(header, counted(records, tally))
    if args.out:
        atomic_write(args.out, lambda f: f.writelines(line.encode("utf-8") for line in lines))
        print(f"{tally['frames']} frames ({tally['refused']} refused, {tally['fallbacks']} fallbacks) -> {args.out}")
    else:
        for line in lines:  # flushed line by line: a reader of the pipe gets each frame as it is done
            sys.stdout.write(line)
            sys.stdout.flush()
    return _points_status(tally, args.points)


def _points_status(tally: Counter, points: str) -> int:
    """The exit code of a --points run: 1 (with one line on stderr) when no frame was rectified."""
    if tally["frames"] > tally["refused"]:
        return 0
    print(
        f"dimenet: {points}: no frame was rectified ({tally['refused']} of {tally['frames']} refused; "
        "each record's error says why)",
        file=sys.stderr,
    )
    return 1


def _check_out(args: argparse.Namespace) -> None:
    """--out is none of the inputs (``cli.outputs``)."""
    if args.out is None:
        return
    camera = None if args.camera is None else camera_file(args.camera)[0]
    inputs = [
        ("DATA", args.data),
        ("--points", args.points),
        ("--model", args.model),
        ("--camera", camera),
        ("--motion", args.motion),
    ]
    refuse_overwriting_inputs("dimenet rectify", [("--out", args.out)], [(n, p) for n, p in inputs if p is not None])


def _motion_options(args: argparse.Namespace) -> dict:
    """The stream's options of --motion (either kind, ``formats.motion``) and --ois-scale."""
    if args.motion is None:
        return {}
    motion = read_motion(args.motion)
    if motion.kind == GYRO:
        if args.ois_scale is not None:
            raise CliError(f"dimenet rectify: --ois-scale scales lens shifts; {args.motion} holds gyroscope rates")
        return {"motion": motion.samples}
    return {"lens_shift": motion.samples, "lens_shift_scale": 1.0 if args.ois_scale is None else args.ois_scale}


def run(args: argparse.Namespace) -> int:
    _check_out(args)
    if args.motion and not args.temporal:
        raise CliError("dimenet rectify: --motion feeds the temporal mode: give --temporal with it")
    if args.ois_scale is not None and not args.motion:
        raise CliError("dimenet rectify: --ois-scale scales a lens-shift --motion file: give --motion with it")
    if args.temporal and not args.points:
        raise CliError("dimenet rectify: --temporal tracks K through a recording: it needs --points FILE")
    if args.points:
        return _run_points(args)
    frames = _frames(args)
    rectifier = _rectifier(args, frames)
    res = rectifier.rectify_batch(
        frames.points_2d, frames.points_3d, frames.valid, infer_mask=frames.infer_mask, refine=args.refine
    )
    arrays = result_arrays(frames, res, rectifier)
    if args.out:
        atomic_write(args.out, lambda f: np.savez(f, **arrays))
    if args.json:
        per_frame = [
            {
                "frame_id": str(arrays["frame_id"][i]),
                "scene": str(frames.scene[i]),
                "e_c_px": float(arrays["e_c"][i]),
                "e_px": float(arrays["e"][i]),
                "K": k_params(arrays["K"][i]).tolist(),
                "K_sigma_px": _k_sigma(arrays, i),
                "fallback": arrays["fallback"][i] or None,
                "fallback_code": arrays["fallback_code"][i] or None,
            }
            for i in range(frames.n_frames)
        ]
        print(
            json.dumps(
                {
                    "model": rectifier.model.source,
                    "model_sha256": rectifier.model.sha256,
                    "mode": args.mode,
                    "refine": args.refine,
                    "K_c": k_params(rectifier.K_c).tolist(),
                    "image_size": list(rectifier.image_size),
                    "frames": per_frame,
                    "summary": _summary(arrays),
                }
            )
        )
    else:
        fx, fy, cx, cy = k_params(rectifier.K_c)
        camera = f"K_c fx={fx:.2f} fy={fy:.2f} cx={cx:.2f} cy={cy:.2f}"
        print(_table(frames, arrays, f"{rectifier.model.source}, mode {args.mode}; {camera}"))
        if args.out:
            print(f"-> {args.out}")
    return 0


COMMAND = Command(
    name="rectify",
    summary="Rectify K frame by frame with a DIME-Net model; print e under K_c and under the rectified K.",
    example="dimenet rectify s8.npz --model s8.onnx --mode map --out s8-rectified.npz\n"
    "  dimenet rectify frames.npz --camera cam.json --json   # the bundled generic model, your camera\n"
    "  dimenet rectify frames.npz --camera cam.json --model paper-rig   # the paper's grid model\n"
    "  dimenet rectify --points rec.csv --camera cam.json --out rec.jsonl   # an app's recording, streamed\n"
    "  dimenet rectify --points rec.csv --camera cam.json --temporal   # K tracked through the recording\n"
    "  dimenet rectify --points rec/points.csv --camera rec/camera.json --temporal --motion rec/gyro.csv  # gyro\n"
    "  dimenet rectify --points rec/points.csv --camera rec/camera.json --temporal --motion rec/ois.csv  # lens shift\n"
    "  dimenet rectify --example",
    add_arguments=add_arguments,
    run=run,
)
