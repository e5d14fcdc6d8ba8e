"""The `dimenet` command line: one parser, subcommands found through entry points.

Each subcommand is a :class:`Command` registered under the ``dimenet.commands`` entry-point
group (see pyproject.toml), so training and export plug in without the runtime importing
them. Bad input exits 2 with one line and no traceback; control characters in it (a file name
holding a newline or an escape code) are printed escaped (``one_line``), so the line stays one
line and nothing reaches the terminal as a control code. Output to a pipe whose reader has gone
(``dimenet rectify --points big.csv | head -1``) ends the command quietly with exit 0. A
character stdout or stderr cannot encode (an ASCII-only terminal, ``PYTHONIOENCODING=ascii``)
is printed as a backslash escape (``±`` as ``\\xb1``), never a traceback after the work is done.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Callable, Optional

from dimenet.runtime import __version__
from dimenet.runtime.errors import DimenetError
from dimenet.runtime.jobs.progress import heartbeat
from dimenet.runtime.plugins import entry_points

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


# C0 and C1 control characters, DEL, and Unicode's line and paragraph separators
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def one_line(message: str) -> str:
    """``message`` with its control characters escaped: a newline as ``\\n``, ESC as ``\\x1b``."""
    return _CONTROL.sub(lambda m: repr(m.group())[1:-1], message)


def _escaping_streams() -> None:
    """Let stdout and stderr print what their encoding cannot hold as backslash escapes."""
    for stream in (sys.stdout, sys.stderr):
        if hasattr(stream, "reconfigure"):
            try:
                stream.reconfigure(errors="backslashreplace")
            except (ValueError, OSError):  # a closed or detached stream: nothing to print to anyway
                pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        raise CliError(f"{self.prog}: {message}")


def _commands() -> list[Command]:
    found = {}
    for ep in entry_points("dimenet.commands").values():
        cmd = ep.load()
        found[cmd.name] = cmd
    return [found[k] for k in sorted(found)]


def version_line() -> str:
    """``dimenet --version``: the version and the implementation running (dimenet.runtime.native: c, the
    compiled core, or python; an ImplementationError for a DIMENET_IMPLEMENTATION it does not know)."""
    from dimenet.runtime.native import implementation

    return f"dimenet {__version__} (implementation {implementation()})"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dimenet",
        description="DIME-Net: rectify an OIS camera's K frame by frame.",
        epilog=EXAMPLE_MAIN,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-V", "--version", action="version", version=version_line())
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
    _escaping_streams()
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "_run", None):
            parser.print_help()
            return 2
        from dimenet.runtime.cli.extras import missing_extras  # after OPENBLAS_NUM_THREADS: it loads numpy

        missing = missing_extras(args.command, args)
        if missing:
            raise CliError(missing)
        with heartbeat(f"dimenet {args.command}"):
            return int(args._run(args) or 0)
    except BrokenPipeError:
        # stdout's reader is gone. As Python's docs advise (signal module, "Note on SIGPIPE"), point
        # stdout at devnull so that the interpreter's flush at exit does not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (DimenetError, OSError) as exc:
        print(f"dimenet: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except ImportError as exc:  # not an extra the command's row names (cli/extras.py): a broken install
        print(
            f"dimenet: error: an import failed ({one_line(str(exc))}): a package dimenet needs is missing or broken",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        print("dimenet: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
