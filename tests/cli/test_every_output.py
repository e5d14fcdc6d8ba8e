"""Every command that writes a file refuses to write over one of its own inputs (issue 48, #5; the rule of
``cli.outputs``): for each (command, output flag, input flag) pair, an output that is the input, or a
symlink to it, exits 2 with one line before anything runs, and the input is left as it was.

The pairs come from ``FLAGS``, which classifies every flag of every command: a new flag, of any kind,
fails ``test_every_flag_of_every_command_is_classified`` until it is classified here, and a new output or
input fails ``test_every_output_input_pair_has_a_case`` until it has a case.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers import importable

from dimenet.runtime.cli.main import build_parser, main

CONTENT = b"precious input\n"
OUT, IN = "writes", "reads"

# What each flag of each command names: OUT a file it writes or a folder it writes files into, IN a file or
# folder it reads; the rest ("other") name no path (numbers, choices, switches, a Ray address).
FLAGS = {
    "bench": {
        "--ingest": OUT,
        "--model": IN,
        "other": "--json --points --frames --threads --batch --callers --budget-ms --refine --mode --n --seed "
        "--profile --workers --bpnp --repeats --baseline-repeats --fuzz --stream",
    },
    "calibrate": {"--out": OUT, "--camera-out": OUT, "data": IN, "other": "--distortion --camera-format"},
    "evaluate": {
        "data": IN,
        "--photos": IN,
        "--model": IN,
        "--camera": IN,
        "other": "--suite --split --drop --noise-2d --noise-3d --eta --grid --seed --methods --json",
    },
    "export": {"--out": OUT, "--golden": OUT, "source": IN, "other": "--graph --format --opset"},
    "fleet": {"--out": OUT, "manifest": IN, "other": "action --quick --address --cpus-per-job"},
    "ingest": {
        "--out": OUT,
        "photos": IN,
        "--rig": IN,
        "--labels": IN,
        "--object": IN,
        "--camera": IN,
        "other": "--split --workers --min-boards --max-megapixels",
    },
    "rectify": {
        "--out": OUT,
        "data": IN,
        "--points": IN,
        "--model": IN,
        "--camera": IN,
        "--motion": IN,
        "other": "--example --mode --refine --json --temporal --ois-scale",
    },
    "render": {"--out": OUT, "--rig": IN, "other": "--profile --n --seed --format --scale --dist-coeffs"},
    "reproduce": {
        "--out": OUT,
        "other": "--data-step --epochs --ablation-epochs --seed --quick --address --cpus-per-job",
    },
    "samples": {"--out": OUT, "other": ""},
    "simulate": {
        "--out": OUT,
        "other": "--profile --family --scenes --seed --natural-frames --planar-frames --dist-coeffs --platform-k "
        "--address --cpus-per-job --recording --seconds --cuts --held-out --ois-off --mislabels",
    },
    "train": {
        "--out": OUT,
        "--resume": OUT,  # the run it continues (its checkpoint names the data and init)
        "data": IN,
        "--init": IN,
        "other": "--quick --grid --features --data-step --moments --head --epochs --seed --focal-weight --k-c-error "
        "--plane-share --train-frames",
    },
}
# Pairs no command line can hold together: the argv that tries, and the line refusing it.
RESUME_ALONE = (
    "but a resumed training keeps the data, init and settings its checkpoint holds: give --resume RUN_DIR alone"
)
UNREACHABLE = {
    ("train", "--resume", "data"): ("train --resume d s8.npz", f"dimenet train --resume: DATA given, {RESUME_ALONE}"),
    ("train", "--resume", "--init"): (
        "train --resume d --init model.onnx",
        f"dimenet train --resume: --init given, {RESUME_ALONE}",
    ),
    ("bench", "--ingest", "--model"): (
        "bench --ingest d --model model.onnx",
        "dimenet bench: --model applies only to the latency bench (without --ingest, --bpnp, --fuzz or --stream) "
        "or --fuzz",
    ),
}
# What a command needs besides the flags under test: files of CONTENT in the current folder.
COMMON_FILES = ("rec.csv", "s8.npz", "cam.json", "rig.json", "photo.jpg", "model.onnx", "labels.csv", "object.csv")
TORCH = ("torch", "safetensors")  # train and export import the train extra before their guard; fleet needs it


@dataclass(frozen=True)
class Case:
    """argv with {in} and {out}; ``written``: the file the command writes, relative to {out} ("" for {out}
    itself); ``victim``: the input file, relative to {in} ("" for {in} itself, else a file of an input folder)."""

    command: str
    out_flag: str
    in_flag: str
    argv: tuple
    written: str = ""
    victim: str = ""
    needs: tuple = None

    def __str__(self) -> str:
        return " ".join(self.argv)


def _cases() -> list:
    def c(command, out_flag, in_flag, argv, written="", victim="", needs=None):
        return Case(command, out_flag, in_flag, tuple(argv.split()), written, victim, needs)

    ingest = "ingest photo.jpg --rig paper --out {out}"
    rectify = "rectify --points rec.csv --camera cam.json --out {out}"
    render = "render --rig {in} --profile galaxy-s8 --n 2 --format png --out {out}"
    return [
        c("calibrate", "--out", "data", "calibrate {in} --out {out}"),
        c("calibrate", "--camera-out", "data", "calibrate {in} --out cal.npz --camera-out {out} --camera-format json"),
        c("export", "--out", "source", "export {in} --out {out}", victim="weights.safetensors", needs=TORCH),
        c("export", "--out", "source", "export {in} --out {out}", victim="spec.json", needs=TORCH),
        c("export", "--out", "source", "export {in} --graph full --out {out}", needs=TORCH),
        c("export", "--out", "source", "export {in} --format ort --out {out}", needs=TORCH),
        c("export", "--golden", "source", "export {in} --golden {out}", written="golden.json", needs=TORCH),
        c("fleet", "--out", "manifest", "fleet train {in} --out {out}", written="summary.json", needs=TORCH),
        c("fleet", "--out", "manifest", "fleet train {in} --out {out}", written="summary.md", needs=TORCH),
        c("ingest", "--out", "photos", "ingest {in} --rig paper --out {out}"),
        c("ingest", "--out", "--rig", "ingest photo.jpg --rig {in} --out {out}"),
        c("ingest", "--out", "--labels", ingest + " --labels {in} --object object.csv"),
        c("ingest", "--out", "--object", ingest + " --labels labels.csv --object {in}"),
        c("ingest", "--out", "--camera", ingest + " --camera {in}"),
        c("rectify", "--out", "data", "rectify {in} --camera cam.json --out {out}"),
        c("rectify", "--out", "--points", "rectify --points {in} --camera cam.json --out {out}"),
        c("rectify", "--out", "--model", "rectify --points rec.csv --model {in} --out {out}"),
        c("rectify", "--out", "--camera", rectify.replace("cam.json", "{in}")),
        c("rectify", "--out", "--motion", rectify + " --temporal --motion {in}"),
        c("render", "--out", "--rig", render, written="truth.npz"),
        c("render", "--out", "--rig", render, written="photo-0001.png"),
        c("train", "--out", "data", "train {in} --out {out}", written="spec.json", needs=TORCH),
        c("train", "--out", "data", "train {in} --out {out}", written="curve.png", needs=TORCH),
        c(
            "train",
            "--out",
            "--init",
            "train s8.npz --out {out} --init {in}",
            "weights.safetensors",
            "weights.safetensors",
            TORCH,
        ),
        c("train", "--out", "--init", "train s8.npz --out {out} --init {in}", written="history.json", needs=TORCH),
    ]


CASES = _cases()


def _subparsers() -> dict:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def _flags(sub: argparse.ArgumentParser) -> set:
    return {a.option_strings[0] if a.option_strings else a.dest for a in sub._actions if a.dest != "help"}


def test_every_flag_of_every_command_is_classified():
    subparsers = _subparsers()
    assert sorted(subparsers) == sorted(FLAGS), "a command was added or removed: classify its flags in FLAGS"
    for name, sub in subparsers.items():
        known = {flag for flag in FLAGS[name] if flag != "other"} | set(FLAGS[name]["other"].split())
        assert _flags(sub) == known, f"dimenet {name}: classify its flags in FLAGS (an output needs a case)"


def test_every_output_input_pair_has_a_case():
    pairs = {
        (name, out, inp)
        for name, flags in FLAGS.items()
        for out, kind in flags.items()
        if kind == OUT
        for inp, other in flags.items()
        if other == IN
    }
    assert pairs - set(UNREACHABLE) == {(c.command, c.out_flag, c.in_flag) for c in CASES}


@pytest.mark.parametrize("pair", sorted(UNREACHABLE))
def test_the_unreachable_pairs_are_refused_together(pair, tmp_path, monkeypatch, capsys, every_extra_present):
    if pair[0] == "train" and not importable(*TORCH):
        pytest.skip("train needs the train extra")
    monkeypatch.chdir(tmp_path)
    Path("model.onnx").write_bytes(CONTENT)
    argv, line = UNREACHABLE[pair]
    assert main(argv.split()) == 2
    assert capsys.readouterr().err == f"dimenet: error: {line}\n"
    assert not Path("d").exists()


def _same(case: Case) -> tuple:
    """(argv values of {in} and {out}, the victim's path) with the input at the very path the command
    writes; None when no path can be both (a folder's file of another name than the one written)."""
    if not case.written:
        return ("d", f"d/{case.victim}", f"d/{case.victim}") if case.victim else ("x", "x", "x")
    if not case.victim:
        return f"d/{case.written}", "d", f"d/{case.written}"
    return ("d", "d", f"d/{case.victim}") if case.victim == case.written else None


def _linked(case: Case, tmp: Path) -> tuple:
    """(argv values of {in} and {out}, the victim's path) with the path the command writes a symlink to
    the input."""
    inp = "i" if not case.victim else "idir"
    victim = Path(inp) / case.victim if case.victim else Path(inp)
    out = "d" if case.written else "link"
    written = Path(out) / case.written if case.written else Path(out)
    written.parent.mkdir(parents=True, exist_ok=True)
    victim.parent.mkdir(parents=True, exist_ok=True)
    written.symlink_to(tmp / victim)
    return inp, out, str(victim)


@pytest.mark.parametrize("how", ["same", "symlink"])
@pytest.mark.parametrize("case", CASES, ids=str)
def test_an_output_that_is_an_input_is_refused(case, how, tmp_path, monkeypatch, capsys):
    if case.needs is not None and not importable(*case.needs):
        pytest.skip(f"{case.command} needs {', '.join(case.needs)} (the train extra)")
    monkeypatch.chdir(tmp_path)
    for name in COMMON_FILES:
        Path(name).write_bytes(CONTENT)
    if how == "same":
        values = _same(case)
        if values is None:
            pytest.skip("no path is both the file written and the input's file")
        inp, out, victim = values
        Path(victim).parent.mkdir(parents=True, exist_ok=True)
    else:
        inp, out, victim = _linked(case, tmp_path)
    Path(victim).write_bytes(CONTENT)
    argv = [a.format(**{"in": inp, "out": out}) for a in case.argv]
    assert main(argv) == 2, argv
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "writing it would replace that file" in err[0], (argv, err)
    assert case.out_flag in err[0], err
    assert Path(victim).read_bytes() == CONTENT
    if how == "symlink":
        written = Path(out) / case.written if case.written else Path(out)
        assert written.is_symlink()


@pytest.mark.skipif(not importable(*TORCH), reason="export imports the train extra before its guard")
def test_export_golden_into_a_link_to_its_model_keeps_the_model(tmp_path, monkeypatch, capsys):
    # issue 48, #5: --golden skipped the guard, so the model file was replaced by the golden JSON, exit 0
    from dimenet.runtime.rectify.model import bundled_model_bytes

    monkeypatch.chdir(tmp_path)
    blob = bundled_model_bytes()
    Path("model.onnx").write_bytes(blob)
    Path("golden").mkdir()
    Path("golden/golden.json").symlink_to(tmp_path / "model.onnx")
    assert main(["export", "model.onnx", "--golden", "golden"]) == 2
    assert capsys.readouterr().err.strip() == (
        "dimenet: error: dimenet export: --golden golden/golden.json is the input SOURCE model.onnx: writing it "
        "would replace that file; choose another --golden"
    )
    assert Path("model.onnx").read_bytes() == blob
