"""The one ``.npz`` reader of every dimenet format (dataset, calibration, render truth).

A ``.npz`` is a zip archive of ``.npy`` members. Before a byte of array data is decoded, the
archive is checked member by member from its zip directory and its ``.npy`` headers alone:

- the file is a zip archive (a ``.npy`` renamed ``.npz``, random bytes, a truncated file: refused);
- each member is ``NAME.npy`` (no duplicates, at most ``MAX_MEMBERS``) with a ``.npy`` header of
  at most ``MAX_HEADER_BYTES`` (read from a bounded prefix of the member, never the data);
- no member holds objects (``allow_pickle`` is never on: nothing is unpickled);
- the member's uncompressed size in the zip directory equals its header plus the data its
  header declares (so a member cannot decompress to more than it declares: a zip bomb is refused
  before decompression), and all members together declare at most ``max_bytes``
  (``MAX_NPZ_BYTES`` by default; every element counts at least one byte).

Decoding then allocates each array once at its declared size and checks every member's CRC-32;
a corrupt or truncated member is refused. Peak memory while reading is therefore the declared
size plus a 256 KiB read buffer. Every refusal is the caller's typed error, naming the file.
"""

from __future__ import annotations

import io
import math
import tokenize
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.lib import format as npy

from dimenet.runtime.errors import DimenetError

MAX_NPZ_BYTES = 1 << 30  # 1 GiB of declared array data per file (see models_spec/dataset-v1.md, "Limits")
MAX_MEMBERS = 64  # no dimenet format has more than 11 arrays
MAX_HEADER_BYTES = 10_000  # numpy's own limit for a .npy header (numpy.lib.format.read_array max_header_size)
_PREFIX_BYTES = 8 + 4 + MAX_HEADER_BYTES  # magic and version, header length, header
_NPY_MAGIC = b"\x93NUMPY"
_ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError, RuntimeError)


def read_npz(
    path: str | Path, error: Callable[[str], DimenetError], what: str, *, max_bytes: int = MAX_NPZ_BYTES
) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``, by name (the member name without ``.npy``).

    ``what`` names the file kind in messages (e.g. ``"dataset file"``). Raises ``error(message)``,
    the message starting with the path, for anything but a sound archive of plain arrays within
    ``max_bytes`` (see the module doc); never unpickles and never decodes a member it has not checked.
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such {what}")
    try:
        with path.open("rb") as f:
            start = f.read(len(_NPY_MAGIC))
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({_reason(exc)})") from None
    if not start:
        raise error(f"{path}: empty file, not a .npz (zip) {what}")
    if start == _NPY_MAGIC:
        raise error(f"{path}: a single .npy array, not a .npz (zip) {what}")
    try:
        archive = zipfile.ZipFile(path)
    except _ZIP_ERRORS as exc:
        raise error(f"{path}: not a .npz (zip) {what} ({_reason(exc)})") from None
    with archive:
        members = _check_members(path, archive, error, max_bytes)
        return {key: _decode(path, archive, info, key, error) for key, info in members.items()}


def _reason(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def _check_members(
    path: Path, archive: zipfile.ZipFile, error: Callable[[str], DimenetError], max_bytes: int
) -> dict[str, zipfile.ZipInfo]:
    """The members by key, each checked from the zip directory and its .npy header alone."""
    infos = archive.infolist()
    if len(infos) > MAX_MEMBERS:
        raise error(f"{path}: {len(infos)} zip members; a dimenet .npz holds at most {MAX_MEMBERS} arrays")
    members: dict[str, zipfile.ZipInfo] = {}
    total = 0
    for info in infos:
        name = info.filename
        if not name.endswith(".npy") or info.is_dir():
            raise error(f"{path}: zip member {name!r} is not a .npy array (a .npz holds only .npy arrays)")
        key = name[: -len(".npy")]
        if key in members:
            raise error(f"{path}: zip member {name!r} appears twice")
        if info.flag_bits & 0x1:
            raise error(f"{path}: {key}: the zip member is encrypted")
        if info.file_size > max_bytes + _PREFIX_BYTES:
            raise error(
                f"{path}: {key}: the zip member decompresses to {info.file_size} bytes; "
                f"a dimenet .npz holds at most {max_bytes} bytes of arrays"
            )
        try:
            with archive.open(info) as stream:
                prefix = stream.read(min(info.file_size, _PREFIX_BYTES))
        except _ZIP_ERRORS as exc:
            raise error(f"{path}: {key}: corrupt zip member ({_reason(exc)})") from None
        header_bytes, shape, dtype = _header(path, key, prefix, error)
        count = math.prod(shape)
        data_bytes = count * dtype.itemsize
        total += max(data_bytes, count)  # an element counts >= 1 byte (a zero-size dtype cannot hide 10^12 of them)
        if total > max_bytes:
            raise error(
                f"{path}: {key}: declares shape {shape} of {dtype} ({data_bytes} bytes); "
                f"a dimenet .npz holds at most {max_bytes} bytes of arrays"
            )
        if info.file_size != header_bytes + data_bytes:
            raise error(
                f"{path}: {key}: the zip member holds {info.file_size} bytes but its .npy header declares "
                f"{header_bytes + data_bytes} (shape {shape} of {dtype}): corrupt or truncated"
            )
        members[key] = info
    return members


def _header(
    path: Path, key: str, prefix: bytes, error: Callable[[str], DimenetError]
) -> tuple[int, tuple[int, ...], np.dtype]:
    """(header length in bytes, shape, dtype) from the first bytes of a member."""
    f = io.BytesIO(prefix)
    try:
        version = npy.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = npy.read_array_header_1_0(f, max_header_size=MAX_HEADER_BYTES)
        elif version == (2, 0):
            shape, _, dtype = npy.read_array_header_2_0(f, max_header_size=MAX_HEADER_BYTES)
        else:
            raise ValueError(f".npy format version {version[0]}.{version[1]} is not supported")
    except (ValueError, TypeError, SyntaxError, EOFError, tokenize.TokenError) as exc:  # the header is a Python literal
        raise error(f"{path}: {key}: not a readable .npy array header ({_reason(exc)})") from None
    if dtype.hasobject:
        raise error(f"{path}: {key}: holds object arrays, which dimenet files forbid (they are never unpickled)")
    if any(n < 0 for n in shape):
        raise error(f"{path}: {key}: its .npy header declares a negative shape {shape}")
    return f.tell(), tuple(int(n) for n in shape), dtype


def _decode(
    path: Path, archive: zipfile.ZipFile, info: zipfile.ZipInfo, key: str, error: Callable[[str], DimenetError]
) -> np.ndarray:
    """The member's array (allocated once at its checked size); its CRC-32 is verified."""
    try:
        with archive.open(info) as stream:
            array = npy.read_array(stream, allow_pickle=False, max_header_size=MAX_HEADER_BYTES)
            if stream.read(1):  # reads to the member's end, which verifies its CRC-32
                raise ValueError("data beyond the declared array")
    except _ZIP_ERRORS as exc:
        raise error(f"{path}: {key}: corrupt or truncated array data ({_reason(exc)})") from None
    return array
