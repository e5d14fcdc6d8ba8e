"""Atomic file writing: a temp file beside the target, then ``os.replace``.

The temp file is ``.NAME.dimenet-HOST-PID-TOKEN.tmp`` in the target's folder: PID is the
writer's process id and HOST a hash of where that id means something (machine name, boot, PID
namespace), so a later write can tell a stale temp file (its writer was killed) from one being
written. Before each write, temp files of the target's own name are removed when stale:

* with this HOST, when process PID no longer exists;
* with another HOST (a shared folder, a container, before a reboot), once not modified for
  ``STALE_AFTER_S`` (an hour): its writer cannot be asked, and no write leaves its temp file
  untouched for that long.

So a live writer's temp file is never removed: a PID that exists keeps its file even if it is
another process by now (the file goes once that one exits). Only names of that pattern, which
has ``dimenet`` in it, are ever removed: a user's own ``.NAME.bak.tmp`` or ``.NAME.k3j_9x0q.tmp``
(tempfile's pattern) stays.

What the target is decides how it is written (models_spec/README.md, "Output paths"):

* a regular file, or nothing: temp file and rename, as above;
* a symbolic link (also one in a chain): the file it resolves to is written so, atomically; the
  link stays a link;
* a character device (``/dev/null``, a terminal, ``/dev/full``) or a FIFO, also through a link
  (``/dev/stdout``): written plainly, in place, never renamed over. A FIFO without a reader is
  a WriteError at once (never a wait). A full device is a WriteError, errno ENOSPC;
* anything else (a block device, a socket): refused with a WriteError; a folder: WriteError.

Permissions: a new file gets the ordinary ``0o666 & ~umask`` (the kernel applies the umask, and
any default ACL, when the temp file is created with mode 0o666: the umask is never read, let
alone set); a file rewritten keeps its mode (a 0600 file stays 0600).

Any OSError while writing is raised as :class:`WriteError` (an OSError, errno kept), whose
message names the target: ``s8.npz: cannot write: No space left on device``.
"""

from __future__ import annotations

import errno
import hashlib
import io
import os
import re
import secrets
import socket
import stat
import time
from pathlib import Path
from typing import BinaryIO, Callable, Optional

STALE_AFTER_S = 3600.0  # a temp file of an unknown writer not modified for this long is stale
TEMP_TAG = "dimenet"  # in every temp file's name: the stale-temp cleanup removes no file without it


class WriteError(OSError):
    """A file could not be written; ``str()`` is ``PATH: cannot ...: PROBLEM`` (errno, strerror and
    filename as an OSError's)."""

    def __str__(self) -> str:
        return f"{self.filename}: {self.strerror}"


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> Path:
    """Call ``write(f)`` on a temp file in the target's folder and rename it over ``path``.

    A failure (exception, full disk, kill) leaves any previous file at ``path`` intact and, but
    for a kill, no temp file (a killed writer's is removed by a later write of the same name).
    Parent folders are created. A symbolic link is followed (the file it resolves to is
    replaced); a character device or FIFO is written in place (see the module doc). Returns the
    path written (``path`` as given); raises :class:`WriteError`.
    """
    path = Path(path)
    kind = _kind(path)
    if kind == "stream":
        _write_in_place(path, write)
        return path
    if kind is not None:
        raise WriteError(errno.EINVAL, f"cannot write: {kind}, not a file (no dimenet output goes there)", str(path))
    target = Path(os.path.realpath(path)) if os.path.islink(path) else path
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _error(path, f"cannot create the folder {target.parent}", exc) from exc
    remove_stale_temps(target)
    mode = _existing_mode(target)
    try:
        fd, tmp = _create_temp(target, 0o666 if mode is None else 0o600)
    except OSError as exc:
        raise _error(path, "cannot create a temp file beside it", exc) from exc
    try:
        try:
            with os.fdopen(fd, "wb") as f:
                if mode is not None:
                    _chmod(f.fileno(), tmp, mode)
                write(f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, target)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
    except WriteError:  # from a nested write in ``write``: it names its own file
        raise
    except OSError as exc:
        raise _error(path, "cannot write", exc) from exc
    return path


class _Stream(io.RawIOBase):
    """A device or FIFO's file descriptor as a write-only stream that cannot seek (``/dev/null``
    seeks but tells 0 whatever was written, which would corrupt a zip's directory)."""

    def __init__(self, fd: int) -> None:
        self._fd = fd

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        return os.write(self._fd, data)

    def close(self) -> None:
        if not self.closed:
            os.close(self._fd)
        super().close()


def _kind(path: Path) -> Optional[str]:
    """What ``path`` is, following links: None for a regular file, nothing, a folder (the
    rename names the problem) or a path that cannot be looked at (the write does);
    ``"stream"`` for a character device or a FIFO; else a few words naming it."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    if stat.S_ISCHR(st.st_mode) or stat.S_ISFIFO(st.st_mode):
        return "stream"
    if stat.S_ISBLK(st.st_mode):
        return "a block device"
    if stat.S_ISSOCK(st.st_mode):
        return "a socket"
    return None


def _write_in_place(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """``write(f)`` on the character device or FIFO ``path`` itself, opened without waiting for
    a FIFO's reader (none: ENXIO, a WriteError)."""
    try:
        fd = os.open(path, os.O_WRONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        if exc.errno == errno.ENXIO:
            raise WriteError(exc.errno, "cannot write: a FIFO with no reader", str(path)) from None
        raise _error(path, "cannot write", exc) from exc
    try:
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)  # the writes wait for a slow reader, as a shell's redirection does
        with io.BufferedWriter(_Stream(fd)) as f:
            write(f)
    except WriteError:
        raise
    except OSError as exc:
        raise _error(path, "cannot write", exc) from exc


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write UTF-8 text atomically."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def temp_name(name: str, pid: Optional[int] = None) -> str:
    """A fresh temp file name for target ``name``, written by process ``pid`` (default: this one)."""
    return f".{name}.{TEMP_TAG}-{_HOST}-{os.getpid() if pid is None else pid}-{secrets.token_hex(4)}.tmp"


def remove_stale_temps(path: str | Path) -> list[Path]:
    """Remove the stale temp files of ``path`` (see the module doc); returns those removed.

    Best effort: a folder that cannot be listed, or a file already gone, is skipped."""
    path = Path(path)
    ours = re.compile(rf"\.{re.escape(path.name)}\.{TEMP_TAG}-([0-9a-f]{{12}})-([0-9]+)-[0-9a-f]{{8}}\.tmp")
    prefix = f".{path.name}.{TEMP_TAG}-"
    removed = []
    try:
        entries = [e for e in os.scandir(path.parent) if e.name.startswith(prefix) and e.name.endswith(".tmp")]
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = ours.fullmatch(entry.name)
        if m is None:
            continue
        try:
            if m.group(1) == _HOST:
                stale = not _alive(int(m.group(2)))
            else:
                stale = now - entry.stat(follow_symlinks=False).st_mtime > STALE_AFTER_S
            if stale and entry.is_file(follow_symlinks=False):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            continue
    return removed


def _host_hash() -> str:
    """12 hex digits naming the space in which this process's PID is meaningful."""
    parts = [socket.gethostname()]
    for read in (
        lambda: Path("/proc/sys/kernel/random/boot_id").read_text().strip(),
        lambda: os.readlink("/proc/self/ns/pid"),
    ):
        try:
            parts.append(read())
        except OSError:
            parts.append("")
    return hashlib.blake2s("\n".join(parts).encode("utf-8", "replace"), digest_size=6).hexdigest()


_HOST = _host_hash()


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (unknown: True)."""
    if os.name != "posix" or pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it exists, another user's
        return True
    return True


def _existing_mode(path: Path) -> Optional[int]:
    """The permission bits of the regular file at ``path``, or None if there is none."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return stat.S_IMODE(st.st_mode) if stat.S_ISREG(st.st_mode) else None


def _create_temp(path: Path, mode: int) -> tuple[int, str]:
    """A new temp file beside ``path``, created with ``mode`` (less the umask): (fd, its path)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0) | getattr(os, "O_CLOEXEC", 0)
    for _ in range(100):
        tmp = os.path.join(path.parent, temp_name(path.name))
        try:
            return os.open(tmp, flags, mode), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temp file name")


def _chmod(fd: int, tmp: str, mode: int) -> None:
    if hasattr(os, "fchmod"):
        os.fchmod(fd, mode)
    else:
        os.chmod(tmp, mode)


def _error(path: Path, action: str, exc: OSError) -> WriteError:
    return WriteError(exc.errno, f"{action}: {exc.strerror or exc}", str(path))
