"""What the camera readers share: checks of values parsed from YAML or a Python literal, the one
YAML loader (YAML 1.2's core schema, as ROS's yaml-cpp reads: ``04032`` is 4032, ``3059:36``
and ``1_000`` are strings, ``yes`` is no boolean), the choice of one camera in a multi-camera
file, and the final ``Camera`` (with the focal-length bound every camera file keeps).

Every problem is a CameraError ``SOURCE: FIELD PROBLEM`` (SOURCE: the file).
"""

from __future__ import annotations

import re
import reprlib
from collections.abc import Mapping, Sequence
from typing import Any, Optional

import numpy as np
import yaml

from dimenet.runtime.errors import CameraError
from dimenet.runtime.json_text import is_number
from dimenet.runtime.rectify.user_camera import DIST_COEFF_COUNTS, Camera, checked_camera

# YAML text is at most this long: PyYAML (pure Python, 3.5 s per MiB) parses 64 KiB in ~0.2 s,
# and a ROS or Kalibr file is ~1 KiB.
MAX_PARSED_CHARS = 64 << 10
MAX_LISTED_NAMES = 8  # a multi-camera file's error lists this many of its camera names

# A value in a message: parsed YAML may share one list a billion times over ("billion laughs"),
# so its repr is bounded in depth and length, never the whole.
_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict, _REPR.maxstring, _REPR.maxother = 3, 6, 4, 40, 40


def shown(value: Any, width: int = 60) -> str:
    """A parsed value for a message: a bounded repr, cut to ``width`` characters."""
    text = _REPR.repr(value)
    return text if len(text) <= width else f"{text[: width - 3]}..."


def fail(source: str, field: str, problem: str) -> CameraError:
    return CameraError(f"{source}: {field} {problem}")


def numbers(value: Any, counts: Sequence[int], source: str, field: str) -> list[float]:
    """``value`` as a list of finite real numbers (no booleans or strings) of one of ``counts`` lengths."""
    wanted = " or ".join(str(n) for n in counts)
    if not isinstance(value, list) or len(value) not in counts:
        raise fail(source, field, f"must be {wanted} numbers, got {shown(value)}")
    out = []
    for v in value:
        if not is_number(v):
            raise fail(source, field, f"must hold finite numbers, got {shown(v)}")
        out.append(float(v))
    return out


def whole(value: Any, source: str, field: str) -> int:
    """An integer (an integral number such as 4032.0 counts, a boolean does not)."""
    if not is_number(value) or value != int(value):
        raise fail(source, field, f"must be an integer, got {shown(value)}")
    return int(value)


def mapping(value: Any, source: str, field: str) -> dict:
    if not isinstance(value, Mapping):
        raise fail(source, field, f"must be a mapping, got {shown(value)}")
    return dict(value)


def required(d: dict, key: str, source: str, where: str = "") -> Any:
    """``d[key]``, or CameraError ``no 'WHEREKEY'`` (``where``: the mapping's own field and a dot)."""
    if key not in d:
        raise CameraError(f"{source}: no {where + key!r}")
    return d[key]


class _CoreSchemaLoader(yaml.SafeLoader):
    """PyYAML's safe loader (no tags beyond YAML's own) with YAML 1.2's core schema for plain
    scalars instead of YAML 1.1's: integers are decimal (``04032`` is 4032; ``0o`` and ``0x``
    name octal and hex), and sexagesimal (``3059:36``), ``1_000``, ``0b1``, ``yes``/``no``/``on``/
    ``off`` are strings; ``1e-05`` is a float (PyYAML's 1.1 rule wants a dot)."""


_CORE_TAGS = {f"tag:yaml.org,2002:{name}" for name in ("bool", "int", "float", "null")}
_CoreSchemaLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in _CORE_TAGS]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
for _tag, _pattern, _first in (
    ("null", r"~|null|Null|NULL|", ["~", "n", "N", ""]),
    ("bool", r"true|True|TRUE|false|False|FALSE", list("tTfF")),
    ("int", r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+", list("-+0123456789")),
    (
        "float",
        r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?|[-+]?\.(inf|Inf|INF)|\.nan|\.NaN|\.NAN",
        list("-+.0123456789"),
    ),
):
    _CoreSchemaLoader.add_implicit_resolver(f"tag:yaml.org,2002:{_tag}", re.compile(f"^(?:{_pattern})$"), _first)


def _core_int(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> int:
    text = loader.construct_scalar(node)
    base = {"0o": 8, "0x": 16}.get(text[:2], 10)
    return int(text[2:] if base != 10 else text, base)


_CoreSchemaLoader.add_constructor("tag:yaml.org,2002:int", _core_int)


def load_yaml(text: str, source: str) -> Any:
    """The value of the YAML ``text`` by PyYAML's safe loader under YAML 1.2's core schema
    (``_CoreSchemaLoader``), at most MAX_PARSED_CHARS long. CameraError naming the line when it is
    not YAML."""
    if len(text) > MAX_PARSED_CHARS:
        raise CameraError(f"{source}: {len(text)} characters of YAML, more than {MAX_PARSED_CHARS} for a camera file")
    try:
        return yaml.load(text, Loader=_CoreSchemaLoader)  # noqa: S506 (a SafeLoader)
    except yaml.MarkedYAMLError as exc:
        where = f"line {exc.problem_mark.line + 1}: " if exc.problem_mark is not None else ""
        raise CameraError(f"{source}: not valid YAML ({where}{exc.problem or exc.context})") from None
    except (yaml.YAMLError, ValueError, RecursionError) as exc:  # ValueError: an int of > 4300 digits
        problem = "nested too deeply" if isinstance(exc, RecursionError) else str(exc).splitlines()[0][:80]
        raise CameraError(f"{source}: not valid YAML ({problem})") from None


def select(names: Sequence[str], name: Optional[str], source: str) -> str:
    """The camera ``name`` of a file holding the cameras ``names`` (in file order); without a
    name, the file's only camera."""
    listed = ", ".join(names[:MAX_LISTED_NAMES]) + (", ..." if len(names) > MAX_LISTED_NAMES else "")
    if not names:
        raise CameraError(f"{source}: holds no camera")
    if name is None:
        if len(names) > 1:
            raise CameraError(f"{source}: holds {len(names)} cameras ({listed}): choose one as {source}#NAME")
        return names[0]
    if name not in names:
        raise CameraError(f"{source}: no camera {name!r} (it holds {listed})")
    return name


def shortest(dist_coeffs: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """OpenCV's coefficients without trailing zeros, down to the shortest count of
    DIST_COEFF_COUNTS (the same lens: OpenCV reads missing coefficients as 0). A count that is
    none of them is left for ``checked_camera`` to refuse."""
    if dist_coeffs is None:
        return None
    d = np.asarray(dist_coeffs, dtype=np.float64).reshape(-1)
    if d.size not in DIST_COEFF_COUNTS:
        return d
    used = np.flatnonzero(d)
    n = int(used[-1]) + 1 if used.size else 0
    return d[: min(c for c in DIST_COEFF_COUNTS if c >= n)]


def camera(K: Any, image_size: Any, source: str, dist_coeffs: Any = None) -> Camera:
    """The checked Camera (``rectify.user_camera.checked_camera``: fx and fy within FOCAL_PER_SIDE
    of the image's larger side, among its rules), its distortion in shortest form."""
    return checked_camera(K, image_size, source, shortest(dist_coeffs))


def padded(camera: Camera, counts: Sequence[int], source: str, form: str) -> list[float]:
    """The camera's distortion (in shortest form) as the shortest of ``counts`` coefficients
    that holds it, zeros appended (no distortion: counts[0] zeros); CameraError when ``form``
    holds none that long."""
    d = [] if camera.dist_coeffs is None else [float(v) for v in shortest(camera.dist_coeffs)]
    fits = [n for n in counts if n >= len(d)]
    if not fits:
        raise fail(
            source, "dist_coeffs", f"of {len(d)} coefficients cannot be written as {form} (at most {counts[-1]})"
        )
    return d + [0.0] * (fits[0] - len(d))


def number(v: float) -> str:
    """A float as text that reads back exactly (Python's shortest repr)."""
    return repr(float(v))


def yaml_number(v: float) -> str:
    """A float as YAML text that reads back exactly, as a float also by PyYAML (``1.0e-05``)."""
    text = repr(float(v))
    mantissa, e, exponent = text.partition("e")
    return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else text


def yaml_list(vs) -> str:
    """Numbers as a YAML flow sequence: ``[1.0, 0.0, 2.5]``."""
    return "[" + ", ".join(yaml_number(v) for v in vs) + "]"
