"""The `dimenet` command line: one parser, subcommands found through entry points.

Each subcommand is a :class:`Command` registered under the ``dimenet.commands`` entry-point
group (see pyproject.toml), so training and export plug in without the runtime importing
them. Bad input exits 2 with one line and no traceback. Output to a pipe whose reader has gone
(``dimenet rectify --points big.csv | head -1``) ends the command quietly with exit 0.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import metadata
from typing import Callable, Optional

from dimenet.runtime import __version__
from dimenet.runtime.errors import DimenetError, InputError
from dimenet.runtime.rectify.grid import Grid

# dimenet solves many tiny batched systems: BLAS threads only contend for the cores (a 1 s
# calibration took 20 s on a busy 2-core machine). Set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

EXAMPLE_MAIN = """examples:
  dimenet simulate --profile galaxy-s8 --out s8.npz
  dimenet evaluate s8.npz --split test
run `dimenet COMMAND --help` for each command's own example."""


@dataclass(frozen=True)
class Command:
    """One subcommand: its help, an example, its arguments and what it runs (returns an exit code)."""

    name: str
    summary: str
    example: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


class CliError(DimenetError):
    """A command-line usage problem (bad flag value, missing extra, ...)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        raise CliError(f"{self.prog}: {message}")


def _commands() -> list[Command]:
    eps = metadata.entry_points()
    group = eps.select(group="dimenet.commands") if hasattr(eps, "select") else eps.get("dimenet.commands", [])
    found = {}
    for ep in group:
        cmd = ep.load()
        found[cmd.name] = cmd
    return [found[k] for k in sorted(found)]


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dimenet",
        description="DIME-Net: rectify an OIS camera's K frame by frame.",
        epilog=EXAMPLE_MAIN,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"dimenet {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for cmd in _commands():
        p = sub.add_parser(
            cmd.name,
            help=cmd.summary,
            description=cmd.summary,
            epilog=f"example:\n  {cmd.example}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "_run", None):
            parser.print_help()
            return 2
        return int(args._run(args) or 0)
    except BrokenPipeError:
        # stdout's reader is gone. As Python's docs advise (signal module, "Note on SIGPIPE"), point
        # stdout at devnull so that the interpreter's flush at exit does not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (DimenetError, OSError) as exc:
        print(f"dimenet: error: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:
        print(
            f"dimenet: error: {exc.name or exc} is not installed; "
            f"this command needs an extra: pip install 'dimenet-runtime[train,export]'",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        print("dimenet: interrupted", file=sys.stderr)
        return 130


# Caps shared by the subcommands' flags (argparse types below). A value past a cap is a typo or
# a value that would hang the command or exhaust memory; each is stated in the error message.
MAX_SEED = 2**32 - 1  # numpy's default_rng takes any int >= 0, torch.manual_seed < 2**64 (train adds 2)
MAX_PARALLEL = 4 * (os.cpu_count() or 1)  # --threads, --workers: more only contend (10**6 hangs)
MAX_GRID = 64  # grid columns and rows each; 64x64 = 4096 cells (100000x100000: MemoryError)
MAX_NOISE = 1000.0  # --noise-2d px, --noise-3d mm: far past any photo's noise (1e300: PnP fails)


def integer_in(minimum: int, maximum: Optional[int] = None) -> Callable[[str], int]:
    """argparse type: an integer in ``minimum`` .. ``maximum`` (no upper bound if None)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"must be <= {maximum}, got {value}")
        return value

    return parse


def integer_at_least(minimum: int) -> Callable[[str], int]:
    """argparse type: an integer >= ``minimum``."""
    return integer_in(minimum)


def finite_float_in(
    minimum: float, maximum: Optional[float] = None, *, above: bool = False, below: bool = False
) -> Callable[[str], float]:
    """argparse type: a finite number in [``minimum``, ``maximum``]; ``above``: > minimum, ``below``: < maximum
    (no upper bound but finiteness if ``maximum`` is None)."""
    lo, hi = ("(" if above else "["), ("inf)" if maximum is None else f"{maximum:g}{')' if below else ']'}")
    interval = f"{lo}{minimum:g}, {hi}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        ok = math.isfinite(value) and (value > minimum if above else value >= minimum)
        if ok and maximum is not None:
            ok = value < maximum if below else value <= maximum
        if not ok:
            raise argparse.ArgumentTypeError(f"must be a finite number in {interval}, got {text}")
        return value

    return parse


def positive_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (value >= 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


seed = integer_in(0, MAX_SEED)
"""argparse type: a random seed, 0 .. 2**32 - 1."""

parallelism = integer_in(1, MAX_PARALLEL)
"""argparse type: a thread or worker-process count, 1 .. 4 x the CPUs."""

noise_sigma = finite_float_in(0.0, MAX_NOISE)
"""argparse type: a noise standard deviation (px or mm), 0 .. 1000."""


def grid_size(text: str) -> str:
    """argparse type: a grid, COLUMNSxROWS (e.g. 8x6), each 1 .. MAX_GRID; returned as 'CxR'."""
    try:
        grid = Grid.parse(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if not (grid.cols <= MAX_GRID and grid.rows <= MAX_GRID):
        raise argparse.ArgumentTypeError(f"columns and rows must each be 1 to {MAX_GRID}, got {text!r}")
    return str(grid)


def nonempty_path(text: str) -> str:
    """argparse type: a file or folder path, not empty or blank (an empty --out would write
    nothing, or into the current folder; an empty --model would quietly mean the default)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"must be a non-empty path, got {text!r}")
    return text


if __name__ == "__main__":
    sys.exit(main())
