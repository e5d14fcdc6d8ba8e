import io
import os
import re
import signal
import subprocess
import sys
import time

import pytest
from helpers import importable

from dimenet.runtime.cli.extras import EXTRAS
from dimenet.runtime.jobs import progress as progress_module
from dimenet.runtime.jobs.progress import LOG_EVERY_S, heartbeat, progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_terminal_gets_a_redrawn_bar_and_the_items_pass_unchanged():
    out = Terminal()
    assert list(progress(range(4), desc="train", stream=out)) == [0, 1, 2, 3]
    text = out.getvalue()
    assert text.count("\r") == 4 and "4/4" in text and text.endswith("\n")


def test_without_a_terminal_a_line_every_log_interval_and_none_for_a_short_job(monkeypatch):
    clock = iter([0.0] + [0.4 * LOG_EVERY_S * k for k in range(1, 11)])  # the start, then one tick per item
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: next(clock))
    out = io.StringIO()
    assert list(progress(range(10), desc="train", stream=out)) == list(range(10))
    lines = out.getvalue().splitlines()
    # 0.4 of the interval per item: a line at items 3, 6 and 9 (1.2 intervals after the last)
    assert [line.split()[1] for line in lines] == ["3/10", "6/10", "9/10"]
    assert all(line.startswith("train ") and line.endswith("s") for line in lines)
    clock = iter([0.0, 1.0, 2.0, 3.0])
    short = io.StringIO()
    assert list(progress(range(3), desc="read", stream=short)) == [0, 1, 2]
    assert short.getvalue() == ""


def _fast_heartbeat(monkeypatch):
    """The heartbeat's intervals cut 50-fold: first line after 0.1 s, then every 0.2 s of silence."""
    monkeypatch.setattr(progress_module, "FIRST_LINE_S", 0.1)
    monkeypatch.setattr(progress_module, "LOG_EVERY_S", 0.2)
    monkeypatch.setattr(progress_module, "TICK_S", 0.01)


def test_the_heartbeat_speaks_first_after_first_line_s_then_after_each_silence(monkeypatch):
    _fast_heartbeat(monkeypatch)
    out = io.StringIO()
    with heartbeat("dimenet reproduce", stream=out):
        time.sleep(0.05)
        assert out.getvalue() == ""  # a command shorter than FIRST_LINE_S says nothing
        time.sleep(0.4)  # 0.1 s: the first line; 0.3 s: the second (0.2 s of silence)
    lines = out.getvalue().splitlines()
    assert len(lines) >= 2 and set(lines) == {"dimenet reproduce: 0 s"}, lines


def test_the_heartbeat_names_the_bars_running_through_one_long_item_and_bars_keep_it_quiet(monkeypatch):
    _fast_heartbeat(monkeypatch)
    out = io.StringIO()
    with heartbeat("dimenet train", stream=out):
        for k in progress(range(3), desc="fit sigma", stream=out):
            time.sleep(0.3 if k == 0 else 0.0)  # one item longer than FIRST_LINE_S: a Ray job, a fit
    lines = out.getvalue().splitlines()
    assert re.fullmatch(r"dimenet train: 0 s, fit sigma 0/3 0\.\ds", lines[0]), lines  # then the bar's own
    out = io.StringIO()
    with heartbeat("dimenet train", stream=out):  # a bar drawing every item: no heartbeat between
        for _ in progress(range(30), desc="train", stream=Terminal()):
            time.sleep(0.01)
    assert out.getvalue() == ""


@pytest.mark.parametrize(
    "argv",
    [["reproduce", "--out", "r"], ["simulate", "--family", "300", "--seed", "0", "--out", "family"]],
    ids=["reproduce", "simulate --family"],
)
def test_a_long_command_says_so_within_ten_seconds(argv, tmp_path):
    """`dimenet reproduce` (9 trainings, ~9 min on 2 cores) wrote nothing for its first 183 s with Ray; the
    heartbeat's first line comes FIRST_LINE_S after the command starts, whatever the command does (simulating
    a family runs ~30 s on the base install)."""
    if argv[0] == "reproduce" and not importable(*EXTRAS["train"]):
        pytest.skip("reproduce needs the train extra")
    start = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "dimenet", *argv],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        first = proc.stderr.readline()
        seconds = time.monotonic() - start
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert first.startswith(f"dimenet {argv[0]}: ") and seconds <= 10.0, (first, seconds)
