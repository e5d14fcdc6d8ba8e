"""A dependency-free progress bar: drawn on a terminal's stderr, silent when piped."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Optional, TypeVar

T = TypeVar("T")


def progress(items: Iterable[T], *, total: Optional[int] = None, desc: str = "", stream=None) -> Iterator[T]:
    """Yield ``items`` unchanged, drawing ``desc [####    ] 12/40 3.1s`` when ``stream`` is a TTY."""
    stream = stream or sys.stderr
    if not getattr(stream, "isatty", lambda: False)():
        yield from items
        return
    total = total if total is not None else (len(items) if hasattr(items, "__len__") else None)  # type: ignore[arg-type]
    start = time.monotonic()
    done = 0
    for item in items:
        yield item
        done += 1
        elapsed = time.monotonic() - start
        if total:
            filled = int(24 * done / total)
            stream.write(f"\r{desc} [{'#' * filled}{' ' * (24 - filled)}] {done}/{total} {elapsed:.1f}s")
        else:
            stream.write(f"\r{desc} {done} {elapsed:.1f}s")
        stream.flush()
    stream.write("\n")
    stream.flush()
