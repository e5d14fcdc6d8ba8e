"""argparse value types of the subcommands' flags, with the caps they enforce: each parses one
string and raises ``argparse.ArgumentTypeError`` with the reason, which argparse turns into the
command's one-line error (exit 2); and the ``--address`` options of the commands whose jobs run on
``jobs.engine``."""

from __future__ import annotations

import argparse
import math
from typing import Callable, Optional

from dimenet.runtime.errors import InputError
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import MAX_THREADS

# Caps shared by the subcommands' flags (argparse types below). A value past a cap is a typo or
# a value that would hang the command or exhaust memory; each is stated in the error message.
MAX_SEED = 2**32 - 1  # numpy's default_rng takes any int >= 0, torch.manual_seed < 2**64 (train adds 2)
MAX_PARALLEL = MAX_THREADS  # --threads, --workers: the API's cap on a session's threads
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
    if "\0" in text:
        raise argparse.ArgumentTypeError(f"a path cannot hold a NUL character, got {text!r}")
    return text


def add_address_argument(p, what: str) -> None:
    """The ``--address`` and ``--cpus-per-job`` options of a command whose jobs are ``what``."""
    p.add_argument(
        "--address",
        metavar="ADDR",
        help=f"run the {what} as Ray jobs (the fleet extra): local or local:N (a cluster on this machine, N CPUs), "
        "auto or ray://host:port (a running one); default: one after another here",
    )
    p.add_argument(
        "--cpus-per-job", type=integer_in(1, 1024), default=1, metavar="N", help="CPUs per Ray job (default 1)"
    )
