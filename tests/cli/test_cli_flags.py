"""Every numeric flag (and every --out) of every subcommand is range-checked by its argparse type:
a bad value exits 2 with one line naming the flag, never a traceback, a hang or a MemoryError.

The commands run in-process with their ``run`` replaced by one that fails the test, so a value
that slips through the parser is caught without starting training, a render or a bench; the
torch commands (train, reproduce, export) are checked the same way, so the check holds without
torch. One subprocess smoke test runs the real entry point.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest

from dimenet.runtime.cli import main as cli
from dimenet.runtime.cli.arguments import MAX_GRID, MAX_NOISE, MAX_PARALLEL, MAX_SEED
from dimenet.runtime.cli.main import build_parser, main

BIG = str(2**40)  # 1099511627776
BASE = {
    "simulate": ["simulate", "--profile", "galaxy-s8", "--out", "s.npz"],
    "calibrate": ["calibrate", "data.npz", "--out", "cal.npz"],
    "evaluate": ["evaluate", "data.npz"],
    "train": ["train", "data.npz", "--out", "run"],
    "reproduce": ["reproduce", "--out", "repro"],
    "export": ["export", "run", "--out", "m.onnx"],
    "rectify": ["rectify", "--example"],
    "bench": ["bench"],
    "bench-ingest": ["bench", "--ingest", "shots"],
    "bench-bpnp": ["bench", "--bpnp"],
    "render": ["render", "--rig", "paper", "--profile", "galaxy-s8", "--n", "1", "--out", "shots"],
    "ingest": ["ingest", "p.jpg", "--rig", "paper", "--out", "d.npz"],
}

SEED = ["-1", str(MAX_SEED + 1), str(2**64), "1.5", "abc", ""]
FLOAT = ["-1", "nan", "inf", "-inf", "1e300", "abc", ""]
PARALLEL = ["0", "-1", str(MAX_PARALLEL + 1), "1000000", BIG, "abc"]
GRID = ["0x6", "8x0", f"{MAX_GRID + 1}x1", "100000x100000", "8", "axb", ""]
OUT = ["", "   "]


def counts(lo: int) -> list:
    return sorted({str(lo - 1), "-1", BIG, "1.5", "abc", ""})


FLAGS = {
    "simulate": {
        "--seed": SEED,
        "--natural-frames": counts(0),
        "--planar-frames": counts(0),
        "--mislabels": FLOAT + ["0.51"],
        "--out": OUT,
    },
    "calibrate": {"--out": OUT},
    "evaluate": {
        "--drop": counts(6),
        "--noise-2d": FLOAT + [str(MAX_NOISE * 1.001)],
        "--noise-3d": FLOAT + [str(MAX_NOISE * 1.001)],
        "--eta": FLOAT + ["1", "1.5"],
        "--grid": GRID,
        "--seed": SEED,
        "--model": OUT,
    },
    "train": {
        "--out": OUT,
        "--grid": GRID,
        "--features": ["BCD", "AB", "", "F", "a"],
        "--epochs": counts(1),
        "--seed": SEED,
        "--focal-weight": FLOAT,
    },
    "reproduce": {"--out": OUT, "--epochs": counts(1), "--ablation-epochs": counts(1), "--seed": SEED},
    "export": {"--out": OUT, "--opset": ["8", "21", "-1", "abc", BIG]},
    "rectify": {"--out": OUT, "--model": OUT},
    "bench": {
        "--points": counts(6),
        "--frames": counts(1),
        "--threads": PARALLEL,
        "--batch": counts(1),
        "--callers": PARALLEL,
        "--budget-ms": FLOAT + ["0"],
        "--model": OUT,
    },
    "bench-ingest": {"--n": counts(1), "--seed": SEED, "--workers": PARALLEL},
    "bench-bpnp": {"--repeats": counts(1), "--baseline-repeats": counts(1)},
    "render": {
        "--n": counts(1),
        "--seed": SEED,
        "--scale": FLOAT + ["0", "0.5", "65"],
        "--dist-coeffs": ["", "abc", "0.1,0.2,0.3", "nan,0,0,0", "1e300,0,0,0"],
        "--out": OUT,
    },
    "ingest": {
        "--out": OUT,
        "--camera": OUT,
        "--min-boards": counts(1),
        "--workers": PARALLEL,
        "--max-megapixels": FLOAT + ["0", "1001"],
    },
}
BAD = [(cmd, flag, value) for cmd, flags in FLAGS.items() for flag, values in flags.items() for value in values]
BAD.append(("bench", "--ingest", ""))

GOOD = [
    ("simulate", "--seed", "0", 0),
    ("simulate", "--seed", str(MAX_SEED), MAX_SEED),
    ("simulate", "--natural-frames", "34", 34),
    ("evaluate", "--drop", "6", 6),
    ("evaluate", "--noise-2d", str(MAX_NOISE), MAX_NOISE),
    ("evaluate", "--noise-3d", "0", 0.0),
    ("evaluate", "--eta", "0.99", 0.99),
    ("evaluate", "--grid", " 8 X 6 ", "8x6"),
    ("evaluate", "--grid", f"{MAX_GRID}x1", f"{MAX_GRID}x1"),
    ("train", "--grid", "1x1", "1x1"),
    ("train", "--features", "E", "E"),
    ("train", "--epochs", "1", 1),
    ("train", "--focal-weight", "0", 0.0),
    ("reproduce", "--ablation-epochs", "150", 150),
    ("export", "--opset", "9", 9),
    ("export", "--opset", "20", 20),
    ("rectify", "--out", "r.npz", "r.npz"),
    ("bench", "--threads", str(MAX_PARALLEL), MAX_PARALLEL),
    ("bench", "--budget-ms", "0.001", 0.001),
    ("bench", "--points", "6", 6),
    ("bench-ingest", "--workers", "1", 1),
    ("render", "--scale", "64", 64.0),
    ("render", "--scale", "1", 1.0),
    ("render", "--dist-coeffs", "0.1,-0.05,0,0", (0.1, -0.05, 0.0, 0.0)),
    ("ingest", "--min-boards", "1", 1),
    ("ingest", "--max-megapixels", "1000", 1000.0),
]


@pytest.fixture
def no_run(monkeypatch):
    """The registered commands with a ``run`` that fails the test: nothing past the parser runs."""
    real = cli._commands()

    def refuse(args):
        pytest.fail(f"the parser let {args} through to the command")

    monkeypatch.setattr(cli, "_commands", lambda: [dataclasses.replace(c, run=refuse) for c in real])


@pytest.mark.parametrize("cmd, flag, value", BAD, ids=[f"{c} {f} {v!r}" for c, f, v in BAD])
def test_a_bad_value_exits_2_with_one_line_naming_the_flag(cmd, flag, value, no_run, capsys):
    # --flag=VALUE: a value starting with '-' is not taken for an option
    assert main([*BASE[cmd], f"{flag}={value}"]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and flag in lines[0] and "Traceback" not in err, err


@pytest.mark.parametrize("cmd, flag, value, parsed", GOOD, ids=[f"{c} {f} {v!r}" for c, f, v, _ in GOOD])
def test_a_good_value_passes_the_parser(cmd, flag, value, parsed):
    args = build_parser().parse_args([*BASE[cmd], flag, value])
    assert getattr(args, flag[2:].replace("-", "_")) == parsed


def test_the_features_choices_are_letters_not_substrings():
    parser = build_parser()
    assert [parser.parse_args([*BASE["train"], "--features", v]).features for v in "ABCDE"] == list("ABCDE")


def test_bench_bpnp_refuses_a_scene_too_big_for_memory_before_importing_torch(capsys, every_extra_present):
    # the baseline's Jacobian is 2N x 3N per frame: --points 100000 would need ~240 GB
    assert main(["bench", "--bpnp", "--points", "100000"]) == 2
    assert main(["bench", "--bpnp", "--frames", "50000", "--points", "2000"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and "--points" in lines[0] and "--frames" in lines[1], lines


def test_smoke_the_real_entry_point_refuses_a_huge_thread_count():
    res = subprocess.run(
        [sys.executable, "-m", "dimenet.runtime.cli.main", "bench", "--threads", "1000000"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "--threads" in lines[0], res.stderr
    assert "Traceback" not in res.stderr
