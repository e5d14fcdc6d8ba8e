import io

from dimenet.runtime.jobs import progress as progress_module
from dimenet.runtime.jobs.progress import LOG_EVERY_S, progress


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
