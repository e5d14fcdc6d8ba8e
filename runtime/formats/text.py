"""Small text files (rigs, label CSVs, camera files): read with a size cap, UTF-8 with an optional
BOM, from regular files only."""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import Optional

from dimenet.runtime.errors import DimenetError
from dimenet.runtime.rectify.clock import MAX_T_NS

_INTEGER = re.compile(r"[+-]?[0-9]+")


def read_text(path: Path, max_bytes: int, what: str, error: type[DimenetError]) -> str:
    """The text of the file ``path`` (``what`` it is, for messages), or ``error`` naming the file
    (and the line of a byte that is not UTF-8): unreadable, not a regular file (a FIFO, a device,
    a folder: opened without waiting for a FIFO's writer, then refused), larger than
    ``max_bytes``, not UTF-8. Reads at most ``max_bytes`` + 1 bytes."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
        try:
            mode = os.fstat(fd).st_mode
            if stat.S_ISREG(mode):
                with os.fdopen(fd, "rb", closefd=False) as f:
                    data = f.read(max_bytes + 1)
        finally:
            os.close(fd)
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc})") from None
    if not stat.S_ISREG(mode):
        raise error(f"{path}: cannot read the {what} ({_kind(mode)}, not a regular file)")
    if len(data) > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes, too large for a {what}")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise error(f"{path}:{line}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def decimal(text: str) -> Optional[float]:
    """The float of a plain decimal in ASCII (``-12.5``, ``.5``, ``3e2``; surrounding whitespace,
    and ``nan``, ``inf``, ``1e400`` as non-finite floats for the caller to refuse), or None: not a
    number, or one Python's float() reads but a data file does not mean (``1_000``, Arabic-Indic or
    full-width digits, Unicode spaces)."""
    if not text.isascii() or "_" in text:
        return None
    try:
        return float(text)
    except ValueError:
        return None


def _kind(mode: int) -> str:
    """What a file that is not a regular file is, in a few words."""
    kinds = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"))
    return next((name for test, name in kinds if test(mode)), "a device or socket")


def t_ns_integer(text: str) -> Optional[int]:
    """The int of a timestamp in ns written as an ASCII integer (``-12``, ``+7``, ``0042``; surrounding whitespace) of
    magnitude at most MAX_T_NS (a signed 64-bit clock), or None (its length is checked before int() reads it, which
    refuses more than 4300 digits)."""
    text = text.strip()
    if not _INTEGER.fullmatch(text) or len(text.lstrip("+-").lstrip("0")) > len(str(MAX_T_NS)):
        return None
    value = int(text)
    return value if abs(value) <= MAX_T_NS else None
