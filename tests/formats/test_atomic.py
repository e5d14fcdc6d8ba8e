"""runtime/formats/atomic.py: modes kept, the umask never touched, stale temp files of killed
writers removed (never a live writer's), and every OSError naming the file."""

from __future__ import annotations

import errno
import io
import os
import pickle
import re
import socket
import stat
import subprocess
import sys
import time

import numpy as np
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
        other_host = tmp_path / f".s8.npz.dimenet-{'0' * 12}-{done.pid}-0123abcd.tmp"
        other_host_old = tmp_path / f".s8.npz.dimenet-{'0' * 12}-{live.pid}-4567cdef.tmp"
        # not dimenet's names, however old: a user's own files, tempfile's pattern, an earlier version's pattern
        strangers = [
            tmp_path / ".s8.npz.backup.tmp",
            tmp_path / temp_name("s8.npz.bak", pid=done.pid),
            tmp_path / ".s8.npz.k3j_9x0q.tmp",
            tmp_path / ".s8.npz.abcd1234.tmp",
            tmp_path / f".s8.npz.{'0' * 12}-{done.pid}-0123abcd.tmp",
        ]
        for p in [dead, alive, mine, old_alive, other_host, other_host_old, *strangers]:
            p.write_bytes(b"partial")
        for p in (old_alive, other_host_old, *strangers):
            os.utime(p, (hour_ago, hour_ago))
        atomic_write(target, lambda f: f.write(b"new"))
    finally:
        live.kill()
        live.wait()
    left = {p.name for p in tmp_path.iterdir()}
    assert target.read_bytes() == b"new"
    assert not {dead.name, other_host_old.name} & left
    assert {alive.name, mine.name, old_alive.name, other_host.name} <= left
    assert {p.name for p in strangers} <= left
    assert len(left) == 1 + 4 + len(strangers)


def test_temp_files_carry_the_project_name():
    assert re.fullmatch(r"\.s8\.npz\.dimenet-[0-9a-f]{12}-[0-9]+-[0-9a-f]{8}\.tmp", temp_name("s8.npz"))


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


# Devices, FIFOs and links (issue 33): written in place or through, never renamed over. Every node
# is made in tmp_path (a copy of /dev/null or /dev/full by os.mknod, as root); nothing outside it
# is ever written.
def char_device(tmp_path, name, like):
    if not hasattr(os, "mknod"):
        pytest.skip("no os.mknod")
    path = tmp_path / name
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.stat(like).st_rdev)
    except PermissionError:
        pytest.skip("making a device node needs root")
    return path


@posix
def test_a_character_device_is_written_in_place_and_stays_a_device(tmp_path):
    null = char_device(tmp_path, "null", "/dev/null")
    atomic_write(null, lambda f: np.savez(f, a=np.zeros(3)))  # a zip on a device that tells 0: no struct.error
    assert stat.S_ISCHR(os.lstat(null).st_mode) and os.listdir(tmp_path) == ["null"]


@posix
def test_a_full_device_reports_enospc_naming_the_file(tmp_path):
    full = char_device(tmp_path, "full", "/dev/full")
    with pytest.raises(WriteError) as exc:
        atomic_write_text(full, "x" * 100)
    assert exc.value.errno == errno.ENOSPC and str(exc.value) == f"{full}: cannot write: No space left on device"
    assert stat.S_ISCHR(os.lstat(full).st_mode)


@posix
def test_a_fifo_is_written_to_its_reader_and_one_without_a_reader_is_refused_at_once(tmp_path):
    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    start = time.monotonic()
    with pytest.raises(WriteError, match=r"out\.fifo: cannot write: a FIFO with no reader"):
        atomic_write_text(fifo, "x")
    assert time.monotonic() - start < 5
    reader = subprocess.Popen(
        [sys.executable, "-c", f"import sys; sys.stdout.buffer.write(open({str(fifo)!r}, 'rb').read())"],
        stdout=subprocess.PIPE,
    )
    for _ in range(500):  # until the reader has the FIFO open
        try:
            atomic_write(fifo, lambda f: np.savez(f, a=np.arange(5)))
            break
        except WriteError:
            time.sleep(0.01)
    data = reader.communicate(timeout=30)[0]
    assert np.load(io.BytesIO(data))["a"].tolist() == [0, 1, 2, 3, 4]
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and os.listdir(tmp_path) == ["out.fifo"]


@posix
def test_a_symlink_stays_a_link_and_its_target_is_replaced_atomically(tmp_path):
    target = tmp_path / "real.json"
    target.write_text("old")
    os.chmod(target, 0o600)
    (tmp_path / "link.json").symlink_to("real.json")
    assert atomic_write_text(tmp_path / "link.json", "new") == tmp_path / "link.json"
    assert os.path.islink(tmp_path / "link.json") and target.read_text() == "new" and mode(target) == 0o600
    (tmp_path / "dangling.json").symlink_to("sub/made.json")
    atomic_write_text(tmp_path / "dangling.json", "d")
    assert os.path.islink(tmp_path / "dangling.json") and (tmp_path / "sub" / "made.json").read_text() == "d"
    assert sorted(os.listdir(tmp_path)) == ["dangling.json", "link.json", "real.json", "sub"]


@posix
def test_a_symlink_to_the_process_stdout_writes_to_stdout_and_stays_a_link(tmp_path):
    link = tmp_path / "stdout.txt"
    link.symlink_to("/proc/self/fd/1")
    code = f"from dimenet.runtime.formats.atomic import atomic_write_text; atomic_write_text({str(link)!r}, 'hello')"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert done.returncode == 0 and done.stdout == b"hello", done.stderr
    assert os.path.islink(link) and os.listdir(tmp_path) == ["stdout.txt"]


@posix
def test_a_socket_is_refused_in_one_line(tmp_path):
    path = tmp_path / "s.sock"
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(path))
        with pytest.raises(WriteError, match=r"s\.sock: cannot write: a socket, not a file"):
            atomic_write_text(path, "x")
    assert stat.S_ISSOCK(os.lstat(path).st_mode)
