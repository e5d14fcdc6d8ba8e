"""The rules of tests/readme_examples.py (CI runs it: the README's shell blocks and every --help example, in
order, in a fresh copy of the checkout), checked against the README and the help in seconds: which blocks
run, how they are cut short, every command line parses as it will run, and no block leaves the shell in
another folder."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from readme_examples import ROOT, Example, cut_short, help_examples, left_out, readme_blocks

from dimenet.runtime.cli.main import CliError, build_parser
from dimenet.runtime.rectify.model import BUNDLED_MODELS


@pytest.fixture(scope="module")
def blocks():
    return readme_blocks((ROOT / "README.md").read_text(encoding="utf-8"))


def test_the_blocks_that_run_and_those_left_out(blocks):
    running = [b for b in blocks if left_out(b) is None]
    assert len(running) >= 8, [b.name for b in blocks]
    assert [left_out(b) for b in blocks if left_out(b) and "dimenet" in b.text] == [
        "needs a running Ray cluster (--address auto)"
    ]


@pytest.mark.parametrize(
    "line, runs",
    [
        (
            "python3 -m venv .venv && . .venv/bin/activate && pip install . && dimenet rectify --example",
            "dimenet rectify --example",
        ),
        (
            "dimenet train family --out runs/generic --epochs 200   # one scale-free model",
            "dimenet train family --out runs/generic --epochs 200 --quick # one scale-free model",
        ),
        ("dimenet simulate --family 60 --seed 0 --out family", "dimenet simulate --family 9 --seed 0 --out family"),
        (
            "dimenet simulate --profile galaxy-s8 --natural-frames 34 --out s8.npz",
            "dimenet simulate --profile galaxy-s8 --natural-frames 34 --out s8.npz",
        ),
        (
            "dimenet render --rig paper --profile galaxy-s8 --n 30 --out shots",
            "dimenet render --rig paper --profile galaxy-s8 --n 6 --out shots",
        ),
        ("dimenet bench --frames 2000 --fuzz=2000", "dimenet bench --frames 200 --fuzz 20"),
        ("dimenet train --resume runs/s8   # stopped", "dimenet train --resume runs/s8 # stopped"),
        (
            "dimenet fleet train d.json --out f --address local:2",
            "dimenet fleet train d.json --out f --address local:2 --quick",
        ),
        ('{"jobs": [{"name": "s8", "epochs": 600}]}', '{"jobs": [{"name": "s8", "epochs": 600}]}'),
    ],
)
def test_long_runs_are_cut_short_with_the_commands_own_flags(line, runs):
    assert cut_short(line) == runs


def _dimenet_lines(examples) -> list:
    lines = []
    for example in examples:
        for line in example.text.splitlines():
            code = re.sub(r"\s\d?>>?\s*\S+", "", cut_short(line).partition(" #")[0])  # no redirections
            lines += [
                part.strip() for part in re.split(r"&&|\|\||;|\(|\)|\|", code) if part.strip().startswith("dimenet ")
            ]
    return lines


def test_every_command_line_parses_as_it_runs(blocks):
    """With --quick and the cut sizes, each README and help command line is one the parser takes."""
    parser = build_parser()
    examples = [b for b in blocks if left_out(b) is None] + help_examples()
    lines = _dimenet_lines(examples)
    assert len(lines) >= 60
    for line in lines:
        argv = shlex.split(line)[1:]
        try:
            args = parser.parse_args([a.replace("*", "x") for a in argv])  # a glob: one of its files
        except CliError as exc:
            pytest.fail(f"{line}: {exc}")
        assert args.command


def test_no_block_leaves_the_shell_in_another_folder(blocks):
    """A `cd` outside a subshell (parentheses) would run the README's next blocks in the wrong folder."""
    for block in blocks + [Example("help", e.text) for e in help_examples()]:
        for line in block.text.splitlines():
            outside = re.sub(r"\([^()]*\)", "", line)
            assert not re.search(r"(^|&&|;|\|\|)\s*cd\s", outside), f"{block.name}: {line}"


def test_files_the_examples_read_come_from_an_earlier_example_or_the_samples(blocks):
    """Each file a command line names as an input (DATA, --points, --camera, --model, MANIFEST...) is written by an
    earlier line (its --out, --camera-out, a heredoc) or by `dimenet samples --out .`."""
    examples = [b for b in blocks if left_out(b) is None] + [e for e in help_examples() if left_out(e) is None]
    written = {*BUNDLED_MODELS, "paper", "../shared/real-photos"}
    for example in examples:
        for line in example.text.splitlines():
            heredoc = re.match(r"cat > (\S+) <<", line)
            if heredoc:
                written.add(heredoc.group(1))
        for line in _dimenet_lines([example]):
            argv = shlex.split(line)
            if argv[:2] == ["dimenet", "samples"]:
                written |= {"frames.npz", "cam.json", "rec.csv"}
            reads = _inputs(argv)
            missing = [p for p in reads if p not in written and not any(p.startswith(w + "/") for w in written)]
            assert not missing, f"{example.name}: {line} reads {missing}, which no earlier example writes"
            written |= _outputs(argv)


def _inputs(argv: list) -> list:
    """The paths a dimenet command line reads: its positional files and the values of its input flags."""
    flags = {"--points", "--camera", "--model", "--init", "--rig", "--resume", "--photos"}
    words = argv[2:]
    if argv[1:3] == ["fleet", "train"]:
        words = argv[3:]
    reads = [w for prev, w in zip([""] + words, words) if prev in flags and not w.isdigit()]  # bench --points N
    positional = [w for prev, w in zip([""] + words, words) if not w.startswith("-") and not prev.startswith("-")]
    return [p.rstrip("/") for p in reads + positional if "*" not in p and p not in ("train",)] + [
        p.split("*")[0].rstrip("/") for p in positional if "*" in p
    ]


def _outputs(argv: list) -> set:
    out = set()
    for flag in ("--out", "--camera-out", "--golden"):
        if flag in argv:
            out.add(argv[argv.index(flag) + 1].rstrip("/"))
    return out


def test_the_runner_is_not_collected_by_pytest():
    assert not Path(__file__).with_name("readme_examples.py").name.startswith("test_")
