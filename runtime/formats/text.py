"""Small text files (rigs, label CSVs): read with a size cap, UTF-8 with an optional BOM."""

from __future__ import annotations

from pathlib import Path

from dimenet.runtime.errors import DimenetError


def read_text(path: Path, max_bytes: int, what: str, error: type[DimenetError]) -> str:
    """The text of the file ``path`` (``what`` it is, for messages), or ``error`` naming the file
    (and the line of a byte that is not UTF-8): unreadable, larger than ``max_bytes``, not UTF-8.
    Reads at most ``max_bytes`` + 1 bytes."""
    try:
        with path.open("rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc})") from None
    if len(data) > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes, too large for a {what}")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise error(f"{path}:{line}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
