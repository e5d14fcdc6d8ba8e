"""`dimenet export`: a RUN_DIR to a ``dimenet-model/1`` ONNX file. torch and onnx are imported only when run."""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

from dimenet.runtime.cli.arguments import integer_in, nonempty_path
from dimenet.runtime.cli.main import CliError, Command
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.rectify.model import BUNDLED_HELP

from .opset import DEFAULT_OPSET, MAX_OPSET, MIN_OPSET


def _add_export(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "source",
        metavar="SOURCE",
        help="a trained model folder from `dimenet train` (RUN_DIR); with --graph full or --golden also a "
        "MODEL.onnx or a bundled model: " + BUNDLED_HELP,
    )
    p.add_argument("--out", type=nonempty_path, metavar="FILE.onnx", help="ONNX file to write (atomically)")
    p.add_argument(
        "--graph",
        choices=("mlp", "full"),
        default="mlp",
        help="mlp: the network alone (features [batch, D] -> delta_k [batch, 4]); full: the whole feature of a "
        "generic model in one graph (a frame's points, K_c, image size and C0 pose -> delta_k, K, sigma px), "
        "for apps in other languages (default mlp)",
    )
    p.add_argument(
        "--format",
        choices=("onnx", "ort"),
        default="onnx",
        help="onnx, or ort: ONNX Runtime's own format for ORT Mobile (iOS, Android), converted with its graph "
        "optimizations off; it keeps the spec and its content_sha256, so the runtime loads and checks it "
        "(--graph mlp; default onnx)",
    )
    p.add_argument(
        "--golden",
        type=nonempty_path,
        metavar="DIR",
        help="instead of a model, write DIR/golden.json: about 20 frames across cameras, scenes and fallbacks "
        "with what the runtime gives for them (models_spec/golden.md)",
    )
    p.add_argument(
        "--opset",
        type=integer_in(MIN_OPSET, MAX_OPSET),
        default=DEFAULT_OPSET,
        help=f"ONNX opset, {MIN_OPSET} to {MAX_OPSET} (default {DEFAULT_OPSET})",
    )


def _model_bytes(source: str, opset: int) -> bytes:
    """The dimenet-model/1 bytes of SOURCE: the bundled model, a MODEL.onnx or a RUN_DIR exported now."""
    from dimenet.runtime.rectify.model import resolve_model

    ref = resolve_model(source)
    if not ref.run_dir:
        return ref.model_bytes()
    from .onnx_export import run_model_bytes

    return run_model_bytes(source, opset=opset)


def _run_export(args: argparse.Namespace) -> int:
    from dimenet.runtime.rectify.model import resolve_model

    if (args.out is None) == (args.golden is None):
        raise CliError("dimenet export: give --out FILE.onnx (a model) or --golden DIR (golden vectors), one of them")
    inputs = [("SOURCE", Path(args.source))]
    ref = resolve_model(args.source)
    if ref.run_dir:  # a RUN_DIR (torch reads it): its files too
        from dimenet.training.run_dir import SPEC, WEIGHTS

        inputs = [("SOURCE", Path(args.source) / name) for name in (WEIGHTS, SPEC)] + inputs
    if args.golden is not None:
        from .golden import GOLDEN_FILE, write_golden

        refuse_overwriting_inputs("dimenet export", [("--golden", Path(args.golden) / GOLDEN_FILE)], inputs)
        path = write_golden(args.golden, args.source)
        print(f"golden vectors of {args.source} -> {path}")
        return 0
    refuse_overwriting_inputs("dimenet export", [("--out", args.out)], inputs)
    blob = _model_bytes(args.source, args.opset)
    if args.graph == "full":
        if args.format == "ort":
            raise CliError("dimenet export: --format ort converts a model (--graph mlp), not the full graph")
        from .full_graph import full_graph

        blob = full_graph(blob, args.source)
    elif args.format == "ort":
        from .onnx_export import ort_format_bytes

        blob = ort_format_bytes(blob, args.source)
    elif not ref.run_dir:
        raise CliError(
            "dimenet export: --graph mlp exports a RUN_DIR (a model file already is one; --format ort converts it)"
        )
    out = Path(atomic_write(args.out, lambda f: f.write(blob)))
    print(
        f"exported {args.source} -> {out} ({args.graph} graph, {args.format}, {len(blob) / 1024:.0f} KiB, "
        f"sha256 {hashlib.sha256(blob).hexdigest()[:16]})"
    )
    return 0


EXPORT = Command(
    name="export",
    summary="Export a trained RUN_DIR to ONNX (features [batch, D] -> delta_k [batch, 4] px, spec in the metadata), "
    "a generic model as one full graph, or golden vectors.",
    example="dimenet export runs/s8 --out s8.onnx --opset 17\n"
    "  dimenet export default --graph full --out dimenet-full.onnx   # points, K_c, pose in; Delta K, K, sigma out\n"
    "  dimenet export default --format ort --out dimenet.ort   # for ORT Mobile\n"
    "  dimenet export default --golden golden/",
    add_arguments=_add_export,
    run=_run_export,
)
