"""A dependency-free progress bar: drawn on a terminal's stderr; without a terminal (a log file, CI,
a pipe) a plain line at most every LOG_EVERY_S seconds, so a long job is seen to be alive."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Optional, TypeVar

T = TypeVar("T")

LOG_EVERY_S = 10.0  # without a terminal: one line when this long has passed since the last (or the start)


def progress(items: Iterable[T], *, total: Optional[int] = None, desc: str = "", stream=None) -> Iterator[T]:
    """Yield ``items`` unchanged, drawing ``desc [####    ] 12/40 3.1s`` when ``stream`` is a TTY, else
    writing ``desc 12/40 31.0s`` lines at most every LOG_EVERY_S s (a job shorter than that writes none)."""
    stream = stream or sys.stderr
    tty = getattr(stream, "isatty", lambda: False)()
    total = total if total is not None else (len(items) if hasattr(items, "__len__") else None)  # type: ignore[arg-type]
    start = last = time.monotonic()
    done = 0
    for item in items:
        yield item
        done += 1
        now = time.monotonic()
        count = f"{done}/{total}" if total else f"{done}"
        if tty:
            bar = f" [{'#' * int(24 * done / total)}{' ' * (24 - int(24 * done / total))}]" if total else ""
            stream.write(f"\r{desc}{bar} {count} {now - start:.1f}s")
        elif now - last >= LOG_EVERY_S:
            stream.write(f"{desc} {count} {now - start:.1f}s\n")
            last = now
        else:
            continue
        stream.flush()
    if tty:
        stream.write("\n")
        stream.flush()
