"""The rule every command with an ``--out`` keeps: an output never replaces one of the command's
inputs (``dimenet rectify --points rec.csv --out rec.csv`` would replace the recording with its
JSON lines). Checked before anything runs; specified in models_spec/README.md, "Output paths"."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import Optional

from dimenet.runtime.cli.main import CliError

Named = tuple[str, "str | Path"]  # (what names it on the command line, e.g. "--points", the path)


def _same(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name one regular file: the same inode (through links, ``..``, a hard link),
    or, where a file is not there yet, the same path once resolved. A device, FIFO or folder is
    never replaced by a write (``formats.atomic``), so it clashes with nothing."""
    sa, sb = _stat(a), _stat(b)
    if any(st is not None and not stat.S_ISREG(st.st_mode) for st in (sa, sb)):
        return False
    if sa is not None and sb is not None:
        return os.path.samestat(sa, sb)
    try:
        return os.path.realpath(a) == os.path.realpath(b)
    except ValueError:  # a NUL in a path: no such file
        return False


def _stat(path: str | Path) -> Optional[os.stat_result]:
    try:
        return os.stat(path)
    except (OSError, ValueError):  # ValueError: a NUL in the path
        return None


def refuse_overwriting_inputs(command: str, outputs: Iterable[Named], inputs: Iterable[Named]) -> None:
    """CliError (one line, exit 2) when one of ``outputs`` is one of ``inputs`` or another of the
    outputs (``calibrate --out a.npz --camera-out a.npz``). ``command``: ``"dimenet rectify"``."""
    outputs, inputs = list(outputs), list(inputs)
    for i, (flag, path) in enumerate(outputs):
        clashes = [("the input", *named) for named in inputs] + [("also the output", *named) for named in outputs[:i]]
        for what, name, other in clashes:
            if _same(path, other):
                raise CliError(
                    f"{command}: {flag} {path} is {what} {name} {other}: writing it would replace that file; "
                    f"choose another {flag}"
                )
