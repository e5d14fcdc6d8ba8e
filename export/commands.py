"""`dimenet export`: a RUN_DIR to a ``dimenet-model/1`` ONNX file. torch and onnx are imported only when run."""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

from dimenet.runtime.cli.arguments import integer_in, nonempty_path
from dimenet.runtime.cli.main import Command
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs

from .opset import DEFAULT_OPSET, MAX_OPSET, MIN_OPSET


def _add_export(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="a trained model folder from `dimenet train`")
    p.add_argument(
        "--out", required=True, type=nonempty_path, metavar="MODEL.onnx", help="ONNX file to write (atomically)"
    )
    p.add_argument(
        "--opset",
        type=integer_in(MIN_OPSET, MAX_OPSET),
        default=DEFAULT_OPSET,
        help=f"ONNX opset, {MIN_OPSET} to {MAX_OPSET} (default {DEFAULT_OPSET})",
    )


def _run_export(args: argparse.Namespace) -> int:
    from dimenet.training.run_dir import SPEC, WEIGHTS

    from .onnx_export import export_run

    inputs = [("RUN_DIR", Path(args.run_dir) / name) for name in (WEIGHTS, SPEC)]
    refuse_overwriting_inputs("dimenet export", [("--out", args.out)], inputs)
    out = Path(export_run(args.run_dir, args.out, opset=args.opset))
    blob = out.read_bytes()
    print(
        f"exported {args.run_dir} -> {out} ({len(blob) / 1024:.0f} KiB, opset {args.opset}, "
        f"sha256 {hashlib.sha256(blob).hexdigest()[:16]})"
    )
    return 0


EXPORT = Command(
    name="export",
    summary="Export a trained RUN_DIR to ONNX (features [batch, D] -> delta_k [batch, 4] px, spec in the metadata).",
    example="dimenet export runs/s8 --out s8.onnx --opset 17",
    add_arguments=_add_export,
    run=_run_export,
)
