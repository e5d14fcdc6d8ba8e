"""runtime/formats/atomic.py: modes kept, the umask never touched, stale temp files of killed
writers removed (never a live writer's), and every OSError naming the file."""

from __future__ import annotations

import errno
import os
import pickle
import stat
import subprocess
import sys
import time

import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats import atomic
from dimenet.runtime.formats.atomic import WriteError, atomic_write, atomic_write_text, temp_name

posix = pytest.mark.skipif(os.name != "posix", reason="POSIX permissions and process ids")


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def no_umask(monkeypatch):
    def refuse(mask):
        raise AssertionError("os.umask called during a write")

    monkeypatch.setattr(atomic.os, "umask", refuse)


@posix
@pytest.mark.parametrize("kept", [0o600, 0o640, 0o444, 0o755])
def test_a_rewritten_file_keeps_its_mode(tmp_path, monkeypatch, kept):
    target = tmp_path / "s8.npz"
    target.write_bytes(b"old")
    os.chmod(target, kept)
    no_umask(monkeypatch)
    atomic_write(target, lambda f: f.write(b"new"))
    assert target.read_bytes() == b"new" and mode(target) == kept


@posix
def test_a_new_file_gets_0666_less_the_umask_without_calling_os_umask(tmp_path, monkeypatch):
    previous = os.umask(0o027)
    try:
        no_umask(monkeypatch)
        atomic_write_text(tmp_path / "a" / "report.json", "{}")
    finally:
        monkeypatch.undo()
        os.umask(previous)
    assert mode(tmp_path / "a" / "report.json") == 0o640


@posix
def test_stale_temp_files_of_dead_writers_go_and_live_writers_stay(tmp_path):
    target = tmp_path / "s8.npz"
    target.write_bytes(b"old")
    done = subprocess.Popen([sys.executable, "-c", "pass"])
    done.wait()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    hour_ago = time.time() - 2 * atomic.STALE_AFTER_S
    try:
        dead = tmp_path / temp_name(target.name, pid=done.pid)
        alive = tmp_path / temp_name(target.name, pid=live.pid)
        mine = tmp_path / temp_name(target.name)
        old_alive = tmp_path / temp_name(target.name, pid=live.pid)  # old, but its writer lives
        legacy_old, legacy_new = tmp_path / ".s8.npz.k3j_9x0q.tmp", tmp_path / ".s8.npz.abcd1234.tmp"
        other_host = tmp_path / f".s8.npz.{'0' * 12}-{done.pid}-0123abcd.tmp"
        other_host_old = tmp_path / f".s8.npz.{'0' * 12}-{live.pid}-4567cdef.tmp"
        strangers = [tmp_path / ".s8.npz.backup.tmp", tmp_path / temp_name("s8.npz.bak", pid=done.pid)]
        for p in [dead, alive, mine, old_alive, legacy_old, legacy_new, other_host, other_host_old, *strangers]:
            p.write_bytes(b"partial")
        for p in (old_alive, legacy_old, other_host_old, *strangers):
            os.utime(p, (hour_ago, hour_ago))
        atomic_write(target, lambda f: f.write(b"new"))
    finally:
        live.kill()
        live.wait()
    left = {p.name for p in tmp_path.iterdir()}
    assert target.read_bytes() == b"new"
    assert not {dead.name, legacy_old.name, other_host_old.name} & left
    assert {alive.name, mine.name, old_alive.name, legacy_new.name, other_host.name} <= left
    assert {p.name for p in strangers} <= left
    assert len(left) == 1 + 5 + len(strangers)


def test_a_full_disk_leaves_the_old_file_and_no_temp_and_names_the_file(tmp_path, monkeypatch):
    target = tmp_path / "s8.npz"
    target.write_bytes(b"old")

    def disk_full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.os, "fsync", disk_full)
    with pytest.raises(OSError) as exc:
        atomic_write(target, lambda f: f.write(b"new"))
    assert isinstance(exc.value, WriteError) and exc.value.errno == errno.ENOSPC
    assert str(exc.value) == f"{target}: cannot write: No space left on device"
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["s8.npz"]


def test_the_cli_reports_a_failed_write_in_one_line_naming_the_file(tmp_path, monkeypatch, capsys):
    out = tmp_path / "rectified.npz"

    def io_error(fd):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(atomic.os, "fsync", io_error)
    assert main(["rectify", "--example", "--json", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"dimenet: error: {out}: cannot write: Input/output error"]
    assert os.listdir(tmp_path) == []


def test_an_exception_of_the_writer_passes_unchanged_and_leaves_no_temp(tmp_path):
    target = tmp_path / "s8.npz"
    target.write_bytes(b"old")

    def broken(f):
        f.write(b"half")
        raise KeyError("boom")

    with pytest.raises(KeyError, match="boom"):
        atomic_write(target, broken)
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["s8.npz"]


def test_a_folder_that_cannot_be_made_is_named(tmp_path):
    (tmp_path / "runs").write_text("a file, not a folder")
    with pytest.raises(WriteError, match=r"runs[/\\]s8[/\\]spec\.json: cannot create the folder .*runs[/\\]s8"):
        atomic_write_text(tmp_path / "runs" / "s8" / "spec.json", "{}")


def test_writing_over_a_folder_is_named_and_leaves_no_temp(tmp_path):
    (tmp_path / "out").mkdir()
    with pytest.raises(WriteError, match=r"out: cannot write: "):
        atomic_write_text(tmp_path / "out", "x")
    assert os.listdir(tmp_path) == ["out"]


def test_the_error_pickles_for_worker_processes(tmp_path):
    err = WriteError(errno.ENOSPC, "cannot write: No space left on device", "s8.npz")
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is WriteError and str(back) == "s8.npz: cannot write: No space left on device"
    assert back.errno == errno.ENOSPC
