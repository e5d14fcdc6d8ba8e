"""The README's shell blocks and every `--help` example, run in order as a newcomer would (issue 52).

CI runs this (`.ci/run`: `python tests/readme_examples.py`, in its full install); it takes minutes, so it
is not a pytest module (tests/test_readme_examples.py checks its rules against the README in seconds). In a
fresh copy of the checkout (its tracked and unignored files) in a temporary folder, with
``../shared/real-photos`` linked beside it where the sets are on this machine:

1. every ```bash block of README.md that calls `dimenet`, in order, each in one bash (``set -euo
   pipefail``) from the copy's root; a block that leaves the shell in another folder fails. Left out: a block
   that needs a running Ray cluster (``--address auto``). A block's install steps (``python3 -m venv``,
   ``. .venv/bin/activate``, ``pip install``) are CI's own, which installed from nothing before this ran;
2. then each `--help`'s examples, `dimenet --help` first, then the commands' in name order, in the same folder.

Long runs are cut short with the commands' own flags (``cut_short``): `dimenet train`, `fleet train` and
`reproduce` get ``--quick``, and the sizes shrink (SIZES). Prints one line per block and example (seconds,
status) and exits 1 when one failed.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
REAL_PHOTOS = ROOT.parent / "shared" / "real-photos"
QUICK = ("dimenet train", "dimenet fleet train", "dimenet reproduce")  # each gets --quick
# flag -> the largest size it runs at (--family 9: the README reads camera 008 of a family)
SIZES = {"--family": 9, "--n": 6, "--fuzz": 20, "--stream": 200, "--frames": 200}
INSTALL = ("python3 -m venv ", ". .venv/bin/activate", "pip install ")  # CI's own steps
CLUSTER = "--address auto"
TIMEOUT_S = 1800


@dataclass(frozen=True)
class Example:
    """One README block (``name`` 'README block N, line L') or --help example, as written."""

    name: str
    text: str


def readme_blocks(text: str) -> list:
    """The README's ```bash blocks, as Examples in order."""
    blocks, lines, inside = [], text.splitlines(), None
    for number, line in enumerate(lines, 1):
        if inside is None and line.strip() == "```bash":
            inside = (number + 1, [])
        elif inside is not None and line.strip() == "```":
            blocks.append(Example(f"README block {len(blocks) + 1} (line {inside[0]})", "\n".join(inside[1])))
            inside = None
        elif inside is not None:
            inside[1].append(line)
    return blocks


def left_out(example: Example) -> Optional[str]:
    """Why an example does not run here, or None."""
    if not re.search(r"(^|[\s(&|;])dimenet\s", example.text):
        return "calls no dimenet command"
    if CLUSTER in example.text:
        return f"needs a running Ray cluster ({CLUSTER})"
    if "../shared/real-photos" in example.text and not REAL_PHOTOS.is_dir():
        return f"the real-photo sets are not on this machine ({REAL_PHOTOS})"
    return None


def cut_short(line: str) -> str:
    """A command line as it runs here: install steps dropped (CI's own), --quick added to a training or
    reproduce, the sizes capped at SIZES'; the comment kept."""
    code, hash_, comment = line.partition(" #")
    parts = [p for p in code.split(" && ") if not p.strip().startswith(INSTALL)]
    code = " && ".join(parts) if parts else ""
    if code.strip().startswith("dimenet "):
        for flag, size in SIZES.items():
            code = re.sub(rf"(?<=\s)({flag})[ =](\d+)", lambda m, s=size: f"{m[1]} {min(int(m[2]), s)}", code)
        if code.strip().startswith(QUICK) and " --resume " not in code:  # a resumed training keeps its settings
            code = code.rstrip() + " --quick"
    return code.rstrip() + (f" {hash_.strip()}{comment}" if hash_ else "")


def help_examples() -> list:
    """Each --help's example lines as Examples: `dimenet --help` first, then the commands' in name order."""
    from dimenet.runtime.cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    texts = [("dimenet --help", parser.format_help())]
    texts += [(f"dimenet {name} --help", sub[name].format_help()) for name in sorted(sub)]
    out = []
    for where, text in texts:
        after = re.split(r"^examples?:$", text, maxsplit=1, flags=re.M)[1]
        for line in after.splitlines():
            if line.strip().startswith("dimenet "):
                out.append(Example(f"{where}: {line.strip()}", line.strip()))
    return out


def script(example: Example) -> str:
    """The bash that runs ``example`` cut short, and fails when it leaves the shell in another folder."""
    body = "\n".join(cut_short(line) for line in example.text.splitlines())
    return (
        f"set -euo pipefail\nstart=$PWD\n{body}\n"
        '[ "$PWD" = "$start" ] || { echo "the block left the shell in $PWD (use a subshell)" >&2; exit 97; }\n'
    )


def fresh_copy(into: Path) -> Path:
    """A copy of the checkout's tracked and unignored files in ``into``/dimenet, with ``into``/shared/real-photos
    linked to this machine's sets (when here)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout
    copy = into / "dimenet"
    for name in filter(None, listed.decode().split("\0")):
        source = ROOT / name
        if source.is_file():
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, copy / name)
    if REAL_PHOTOS.is_dir():
        (into / "shared").mkdir()
        (into / "shared" / "real-photos").symlink_to(REAL_PHOTOS)
    return copy


def run(example: Example, cwd: Path, env: dict) -> tuple:
    """(exit code, seconds, the output's last lines) of ``example`` run in ``cwd``."""
    start = time.monotonic()
    try:
        done = subprocess.run(
            ["bash", "-c", script(example)], cwd=cwd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S
        )
        code, output = done.returncode, done.stdout + done.stderr
    except subprocess.TimeoutExpired as exc:
        code, output = 124, f"timed out after {TIMEOUT_S} s ({exc})"
    return code, time.monotonic() - start, output.strip().splitlines()[-12:]


def main() -> int:
    examples = readme_blocks((ROOT / "README.md").read_text(encoding="utf-8")) + help_examples()
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    failed, start = [], time.monotonic()
    with tempfile.TemporaryDirectory(prefix="dimenet-readme-") as folder:
        copy = fresh_copy(Path(folder))
        print(f"in a fresh copy of the checkout: {copy}", flush=True)
        for example in examples:
            reason = left_out(example)
            if reason is not None:
                print(f"   -  {example.name}: left out, {reason}", flush=True)
                continue
            code, seconds, tail = run(example, copy, env)
            print(f"{seconds:6.1f} s  {'ok' if code == 0 else f'FAILED (exit {code})'}  {example.name}", flush=True)
            if code != 0:
                failed.append(example.name)
                print("\n".join(f"          | {line}" for line in [*script(example).splitlines()[2:-1], "--", *tail]))
    print(f"{len(examples)} examples, {len(failed)} failed, {time.monotonic() - start:.0f} s", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
