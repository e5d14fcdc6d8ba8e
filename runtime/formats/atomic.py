"""Atomic file writing: a temp file beside the target, then ``os.replace``.

The temp file is ``.NAME.HOST-PID-TOKEN.tmp`` in the target's folder: PID is the writer's
process id and HOST a hash of where that id means something (machine name, boot, PID
namespace), so a later write can tell a stale temp file (its writer was killed) from one being
written. Before each write, temp files of the target's own name are removed when stale:

* ``.NAME.HOST-PID-TOKEN.tmp`` with this HOST whose process PID no longer exists;
* ``.NAME.XXXXXXXX.tmp`` (tempfile's pattern, left by earlier versions) or one with another HOST
  (a shared folder, a container, before a reboot), once not modified for ``STALE_AFTER_S`` (an
  hour): its writer cannot be asked, and no write leaves its temp file untouched for that long.

So a live writer's temp file is never removed: a PID that exists keeps its file even if it is
another process by now (the file goes once that one exits). Files of any other name are never
touched.

Permissions: a new file gets the ordinary ``0o666 & ~umask`` (the kernel applies the umask, and
any default ACL, when the temp file is created with mode 0o666: the umask is never read, let
alone set); a file rewritten keeps its mode (a 0600 file stays 0600).

Any OSError while writing is raised as :class:`WriteError` (an OSError, errno kept), whose
message names the target: ``s8.npz: cannot write: No space left on device``.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import secrets
import socket
import stat
import time
from pathlib import Path
from typing import BinaryIO, Callable, Optional

STALE_AFTER_S = 3600.0  # a temp file of an unknown writer not modified for this long is stale


class WriteError(OSError):
    """A file could not be written; ``str()`` is ``PATH: cannot ...: PROBLEM`` (errno, strerror and
    filename as an OSError's)."""

    def __str__(self) -> str:
        return f"{self.filename}: {self.strerror}"


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> Path:
    """Call ``write(f)`` on a temp file in the target's folder and rename it over ``path``.

    A failure (exception, full disk, kill) leaves any previous file at ``path`` intact and, but
    for a kill, no temp file (a killed writer's is removed by a later write of the same name).
    Parent folders are created. Returns the path written; raises :class:`WriteError`.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _error(path, f"cannot create the folder {path.parent}", exc) from exc
    remove_stale_temps(path)
    mode = _existing_mode(path)
    try:
        fd, tmp = _create_temp(path, 0o666 if mode is None else 0o600)
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
            os.replace(tmp, path)
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


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write UTF-8 text atomically."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def temp_name(name: str, pid: Optional[int] = None) -> str:
    """A fresh temp file name for target ``name``, written by process ``pid`` (default: this one)."""
    return f".{name}.{_HOST}-{os.getpid() if pid is None else pid}-{secrets.token_hex(4)}.tmp"


def remove_stale_temps(path: str | Path) -> list[Path]:
    """Remove the stale temp files of ``path`` (see the module doc); returns those removed.

    Best effort: a folder that cannot be listed, or a file already gone, is skipped."""
    path = Path(path)
    ours = re.compile(rf"\.{re.escape(path.name)}\.([0-9a-f]{{12}})-(\d+)-[0-9a-f]{{8}}\.tmp")
    legacy = re.compile(rf"\.{re.escape(path.name)}\.[a-z0-9_]{{8}}\.tmp")
    prefix = f".{path.name}."
    removed = []
    try:
        entries = [e for e in os.scandir(path.parent) if e.name.startswith(prefix) and e.name.endswith(".tmp")]
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = ours.fullmatch(entry.name)
        try:
            if m and m.group(1) == _HOST:
                stale = not _alive(int(m.group(2)))
            elif m or legacy.fullmatch(entry.name):
                stale = now - entry.stat(follow_symlinks=False).st_mtime > STALE_AFTER_S
            else:
                continue
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
