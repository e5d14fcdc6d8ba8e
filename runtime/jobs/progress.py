"""A dependency-free progress bar, and a heartbeat for the whole of a command.

``progress`` draws a bar on a terminal's stderr; without a terminal (a log file, CI, a pipe) it writes a
plain line at most every LOG_EVERY_S seconds. ``heartbeat`` (the `dimenet` command runs inside one)
writes a line whenever stderr has had none for LOG_EVERY_S seconds, the first FIRST_LINE_S seconds
after the start: the command, its seconds so far and the bars running (``dimenet reproduce: 40 s,
reproduce: training 2/13``). So a long command is seen to be alive from its first seconds on, also
through a step that draws no bar (a Ray job, a fit) or a single long item; a command shorter than
FIRST_LINE_S writes none.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Optional, TypeVar

T = TypeVar("T")

LOG_EVERY_S = 10.0  # without a terminal: one line when this long has passed since the last (or the start)
FIRST_LINE_S = 5.0  # the heartbeat's first line, when nothing was written before
TICK_S = 0.5  # how often the heartbeat looks

_lock = threading.Lock()
_running: list = []  # the bars drawing now, outermost first
_last_line = [time.monotonic()]  # when a bar or the heartbeat last wrote


class _Bar:
    def __init__(self, desc: str, total: Optional[int], stream) -> None:
        self.desc, self.total, self.stream = desc, total, stream
        self.tty = getattr(stream, "isatty", lambda: False)()
        self.done = 0
        self.start = self.last = time.monotonic()

    def text(self, now: float) -> str:
        count = f"{self.done}/{self.total}" if self.total else f"{self.done}"
        return f"{self.desc} {count} {now - self.start:.1f}s"

    def draw(self, now: float) -> None:
        """Redraw the bar on a terminal, else write a line; under the lock."""
        if self.tty:
            filled = int(24 * self.done / self.total) if self.total else 0
            bar = f" [{'#' * filled}{' ' * (24 - filled)}]" if self.total else ""
            count = f"{self.done}/{self.total}" if self.total else f"{self.done}"
            self.stream.write(f"\r{self.desc}{bar} {count} {now - self.start:.1f}s")
        else:
            self.stream.write(self.text(now) + "\n")
        self.stream.flush()
        self.last = _last_line[0] = now


def progress(items: Iterable[T], *, total: Optional[int] = None, desc: str = "", stream=None) -> Iterator[T]:
    """Yield ``items`` unchanged, drawing ``desc [####    ] 12/40 3.1s`` when ``stream`` is a TTY, else
    writing ``desc 12/40 31.0s`` lines at most every LOG_EVERY_S s (a job shorter than that writes none)."""
    total = total if total is not None else (len(items) if hasattr(items, "__len__") else None)  # type: ignore[arg-type]
    bar = _Bar(desc, total, stream or sys.stderr)
    with _lock:
        _running.append(bar)
    try:
        for item in items:
            yield item
            bar.done += 1
            now = time.monotonic()
            if bar.tty or now - bar.last >= LOG_EVERY_S:
                with _lock:
                    bar.draw(now)
    finally:
        with _lock:
            _running.remove(bar)
            if bar.tty:
                bar.stream.write("\n")
                bar.stream.flush()


def _beat(label: str, start: float, stream) -> None:
    """One heartbeat line, or on a terminal a redraw of the innermost bar; under the lock."""
    now = time.monotonic()
    if _running and _running[-1].tty:
        _running[-1].draw(now)
        return
    bars = "".join(f", {bar.text(now)}" for bar in _running)
    stream.write(f"{label}: {now - start:.0f} s{bars}\n")
    stream.flush()
    _last_line[0] = now


@contextmanager
def heartbeat(label: str, stream=None):
    """While the body runs, ``label: S s[, each running bar]`` on ``stream`` (default: stderr at the time)
    whenever no line was written for LOG_EVERY_S s, the first FIRST_LINE_S s after the start."""
    start = time.monotonic()
    stop = threading.Event()
    with _lock:
        _last_line[0] = start - (LOG_EVERY_S - FIRST_LINE_S)

    def beat() -> None:
        while not stop.wait(TICK_S):
            with _lock:
                if time.monotonic() - _last_line[0] >= LOG_EVERY_S:
                    try:
                        _beat(label, start, stream or sys.stderr)
                    except (OSError, ValueError):  # stderr closed or its reader gone: nothing to tell
                        return

    thread = threading.Thread(target=beat, name="dimenet-heartbeat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
