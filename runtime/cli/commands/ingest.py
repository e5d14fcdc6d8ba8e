"""`dimenet ingest`: photos of the rig (and of a natural object with labelled points) -> a dataset."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from dimenet.runtime.cli.arguments import finite_float_in, integer_in, nonempty_path, parallelism
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs
from dimenet.runtime.errors import IngestError
from dimenet.runtime.formats.atomic import atomic_write_text
from dimenet.runtime.formats.camera_file import camera_file, read_camera
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.formats.natural_labels import read_labels, read_object
from dimenet.runtime.formats.rig import MAX_RIG_POINTS, PAPER_RIG_NAME, rig_from_argument
from dimenet.runtime.geometry import spans_3d
from dimenet.runtime.ingest.outcome import DROPPED, IDENTIFIED, NOT_FOUND
from dimenet.runtime.ingest.photo import MAX_MEGAPIXELS
from dimenet.runtime.ingest.pipeline import MIN_BOARDS, SPLITS, check_object, ingest, report
from dimenet.runtime.jobs.progress import progress

# A set of fewer views than this, all of one board, is told how many views --split auto holds out of K_c.
SMALL_SET = 30
OPENCV_MAX_MEGAPIXELS = 1000.0  # OpenCV refuses to decode more than 2**30 px (1073.7 MP) whatever the flag


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "photos", nargs="+", metavar="PHOTO", help="photos of the rig (JPEG, PNG, TIFF, ...); frames keep this order"
    )
    p.add_argument("--rig", required=True, help="rig file (dimenet-rig/1 JSON), or `paper` for the bundled paper rig")
    p.add_argument(
        "--out",
        required=True,
        type=nonempty_path,
        help="dataset file to write (dimenet-dataset/1 .npz); the report goes beside it as <name>.report.json",
    )
    p.add_argument(
        "--split",
        choices=SPLITS,
        default="auto",
        help="split of every frame; auto (default): 80/20 train/test by file-name hash, natural photos test "
        f"(a set of fewer than {SMALL_SET} views of one board is told how many it holds out of K_c)",
    )
    p.add_argument("--labels", metavar="LABELS.csv", help="hand-labelled natural points: image,point_id,x_px,y_px")
    p.add_argument(
        "--object", metavar="OBJECT.csv", help="the natural object's points in the rig frame: point_id,X_mm,Y_mm,Z_mm"
    )
    p.add_argument(
        "--workers",
        type=parallelism,
        default=1,
        help="photos processed in parallel (two threads, then processes beyond two; results in the photos' order "
        "whatever N; default 1)",
    )
    p.add_argument(
        "--min-boards",
        type=integer_in(1, MAX_RIG_POINTS),  # a rig has fewer boards than corners; its own count is checked next
        metavar="N",
        help=f"boards a rig photo needs, at most the rig's (default: 1 for a one-board rig, whose photos are planar "
        f"frames, else {MIN_BOARDS}); a labelled photo needs 1",
    )
    p.add_argument(
        "--camera",
        type=nonempty_path,
        metavar="FILE",
        help="the photos' camera file with its lens (OpenCV YAML/XML, ROS, COLMAP, Kalibr, mrcal, camera.json): "
        "a photo of another image size is skipped, each photo's K in the report is fitted under the lens, and "
        "the dataset carries it (dist_coeffs about the file's K), so calibrate, train, evaluate and rectify "
        "undistort with it",
    )
    p.add_argument(
        "--max-megapixels",
        type=finite_float_in(0.0, OPENCV_MAX_MEGAPIXELS, above=True),
        default=MAX_MEGAPIXELS,
        metavar="N",
        help=f"skip a photo whose header declares more than N megapixels, before decoding it (default "
        f"{MAX_MEGAPIXELS:g}: 48 MP sensors pass; at most {OPENCV_MAX_MEGAPIXELS:g})",
    )


def report_path(out: str | Path) -> Path:
    """Where the JSON report of a dataset goes: DATA.npz -> DATA.report.json."""
    out = Path(out)
    return out.with_name(f"{out.stem}.report.json")


def board_text(line: dict) -> str:
    """One board's line of the printed report (indented under its photo)."""
    name = line["board"] or f"{line['pattern'][0]}x{line['pattern'][1]} board"
    if line["status"] == NOT_FOUND:
        return f"    {name}: not found" + (f" ({line['why']})" if line["why"] else "")
    fit = (
        ""
        if line["residual_px"] is None
        else f"; residual {line['residual_px']:.1f} px, tolerance {line['tolerance_px']:.1f} px"
    )
    if line["status"] == DROPPED:
        return f"    {name}: found ({line['found_by']}), dropped: {line['why']}"
    return f"    {name}: {line['status']} ({line['found_by']}{fit})"


def printed_board_lines(p: dict) -> list[str]:
    """The board lines printed under a photo: all of a skipped photo's; an accepted photo's boards dropped and
    in view but not found."""
    lines = p["board_lines"]
    if p["skipped"] is None:
        lines = [b for b in lines if b["status"] == DROPPED or (b["status"] == NOT_FOUND and b["why"] != "not in view")]
    return [board_text(b) for b in lines if p["skipped"] is not None or b["status"] != IDENTIFIED]


def photo_line(p: dict) -> str:
    """One photo's line of the printed report, then its board lines (``printed_board_lines``)."""
    boards = "".join("\n" + line for line in printed_board_lines(p))
    if p["skipped"] is not None:
        return f"{p['photo']}  skipped: {p['skipped']}{boards}"
    labels = f" + {p['labels']} labels" if p["labels"] else ""
    exif = f"  (EXIF orientation {p['exif_orientation']} not applied)" if p["exif_orientation"] != 1 else ""
    fit = "  planar (one board: no K)" if p["K_px"] is None else f"  RMS {p['rms_px']:.3f} px"
    return (
        f"{p['photo']}  {p['split']}  {len(p['boards'])} boards ({', '.join(p['boards'])})  {p['corners']} corners"
        f"{labels}{fit}{exif}{boards}"
    )


def run(args: argparse.Namespace) -> int:
    if (args.labels is None) != (args.object is None):
        raise CliError("dimenet ingest: --labels and --object go together")
    inputs = [("PHOTO", p) for p in args.photos] + [
        (flag, path)
        for flag, path in (
            ("--rig", None if args.rig == PAPER_RIG_NAME else args.rig),
            ("--labels", args.labels),
            ("--object", args.object),
            ("--camera", None if args.camera is None else camera_file(args.camera)[0]),
        )
        if path is not None
    ]
    outputs = [("--out", args.out), ("--out's report", report_path(args.out))]
    refuse_overwriting_inputs("dimenet ingest", outputs, inputs)
    camera = read_camera(args.camera) if args.camera else None
    rig = rig_from_argument(args.rig)
    obj = read_object(args.object) if args.object else None
    if obj is not None:
        check_object(obj, args.object)
    labels = read_labels(args.labels, obj) if obj is not None else None
    start = time.monotonic()
    result = ingest(
        args.photos,
        rig,
        split=args.split,
        obj=obj,
        labels=labels,
        workers=args.workers,
        progress=lambda items: progress(items, total=len(args.photos), desc="ingest"),
        max_megapixels=args.max_megapixels,
        min_boards=args.min_boards,
        camera=camera,
    )
    seconds = time.monotonic() - start
    rep = report(result, rig)
    for p in rep["photos"]:
        print(photo_line(p))
    text = json.dumps(rep, indent=1) + "\n"
    if result.dataset is None:  # nothing to write but the report, which says so (0 frames)
        where = atomic_write_text(report_path(args.out), text)
        raise IngestError(f"no photo gave a frame (report: {where})")
    path = write_dataset(result.dataset, args.out)  # first: a report never claims a dataset that is not there
    where = atomic_write_text(report_path(args.out), text)
    t = rep["totals"]
    print(
        f"{t['frames']} frames ({t['splits']['train']} train, {t['splits']['test']} test) from {t['photos']} photos, "
        f"{t['skipped']} skipped; {t['boards']} boards, {t['corners']} corners; "
        f"{t['photos'] / seconds:.1f} photos/s -> {path} (report: {where})"
    )
    if camera is not None:
        lens = "no distortion" if camera.dist_coeffs is None else f"{len(camera.dist_coeffs)} distortion coefficients"
        print(f"lens: {lens} from {args.camera}")
    note = held_out_note(args.split, result.dataset)
    if note:
        print(note)
    return 0


def held_out_note(split: str, dataset) -> str:
    """Under ``--split auto``, for a set of fewer than SMALL_SET views all of one plane (one board): how many
    views the test split holds out of K_c (``calibrate`` averages the train views), and how to keep them."""
    if split != "auto" or dataset.n_frames >= SMALL_SET:
        return ""
    planar = [not spans_3d(x[v]) for x, v in zip(dataset.points_3d, dataset.valid)]
    test = int(dataset.frames_in("test").sum())
    if not all(planar) or test == 0:
        return ""
    return (
        f"note: --split auto holds {test} of these {dataset.n_frames} views of one board out of K_c (the test "
        f"split, ~20 % by file name); with fewer than {SMALL_SET} views each counts: --split train keeps them all "
        "for K_c (`dimenet evaluate` then measures them against their homography floor with --split train)"
    )


COMMAND = Command(
    name="ingest",
    summary="Turn photos of the rig (and of a natural object with labelled points) into a dataset: find, refine "
    "and identify every board, fit each photo's K, report per photo.",
    example="dimenet ingest shots/*.jpg --rig paper --out s8-photos.npz --workers 2   # shots: `dimenet render`",
    add_arguments=add_arguments,
    run=run,
)
