"""JSON text inside dimenet files (a model spec, a dataset's ``meta``, a rig file): parsed with
limits, and its fields read with checks.

``json.loads`` alone raises RecursionError on deeply nested input (``"[" * 100000``) and
ValueError on integers of more than 4300 digits, and it keeps the last of duplicated keys. Here
every such input, and every field of the wrong type, shape or range, is a ``JsonProblem`` (a
ValueError) the caller turns into its typed error naming the file.
"""

from __future__ import annotations

import json
import math
from typing import Any, Optional

import numpy as np

MAX_JSON_DEPTH = 32  # nesting of arrays and objects; dimenet's deepest (a rig inside a dataset's meta) is 5


class JsonProblem(ValueError):
    """Why a JSON text was refused (``line``: where, when known)."""

    def __init__(self, problem: str, line: Optional[int] = None) -> None:
        super().__init__(problem if line is None else f"{problem}, line {line}")
        self.problem, self.line = problem, line


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    d = dict(pairs)
    if len(d) != len(pairs):
        seen: set[str] = set()
        key = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise JsonProblem(f"key {key!r} appears twice in one object")
    return d


def parse_json(text: str, *, max_chars: int, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """The value of the JSON ``text``. Raises JsonProblem: longer than ``max_chars``, not JSON,
    nested deeper than ``max_depth``, a duplicated key, a number too long to convert."""
    if len(text) > max_chars:
        raise JsonProblem(f"longer than {max_chars} characters ({len(text)})")
    try:
        value = json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as exc:
        raise JsonProblem(exc.msg, exc.lineno) from None
    except RecursionError:
        raise JsonProblem(f"nested deeper than {max_depth} levels") from None
    except JsonProblem:
        raise
    except ValueError as exc:  # e.g. an integer of more than 4300 digits
        raise JsonProblem(str(exc).split(";")[0]) from None
    _check_depth(value, max_depth)
    return value


def _check_depth(value: Any, max_depth: int) -> None:
    stack = [(value, 1)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, (dict, list)):
            if depth > max_depth:
                raise JsonProblem(f"nested deeper than {max_depth} levels")
            children = v.values() if isinstance(v, dict) else v
            stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))


def shown(value: Any, width: int = 60) -> str:
    """A field's value for a message: its repr, cut to ``width`` characters."""
    text = repr(value)
    return text if len(text) <= width else f"{text[: width - 3]}..."


def is_number(value: Any) -> bool:
    """A finite JSON number: a float, or an int a float holds (never a bool or a string)."""
    kind = type(value)
    if kind is float:
        return math.isfinite(value)
    return kind is int and -1e300 <= value <= 1e300


def numbers(value: Any, shape: tuple, name: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` (one or two axes): nested JSON lists of finite
    numbers, exactly (no strings, no booleans, no ragged lists)."""
    rows, n_rows = (value, shape[0]) if len(shape) == 2 else ([value], 1)
    if not isinstance(rows, list) or len(rows) != n_rows:
        raise JsonProblem(f"{name} must be {' x '.join(map(str, shape))} numbers, got {shown(value)}")
    for row in rows:
        if not isinstance(row, list) or len(row) != shape[-1]:
            raise JsonProblem(f"{name} must be {' x '.join(map(str, shape))} numbers, got {shown(value)}")
        for v in row:
            if not is_number(v):
                raise JsonProblem(f"{name} must hold finite numbers, got {shown(v)}")
    return np.array(value, dtype=np.float64)


def integer(value: Any, name: str, low: int, high: Optional[int] = None) -> int:
    """An integer (an integral JSON number) in [low, high]."""
    if not is_number(value) or value != int(value):
        raise JsonProblem(f"{name} must be an integer, got {shown(value)}")
    if value < low or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"{low} to {high}"
        raise JsonProblem(f"{name} must be {bound}, got {shown(value)}")
    return int(value)


def required(d: dict, key: str, where: str = "") -> Any:
    """``d[key]``, or JsonProblem naming the missing field."""
    if key not in d:
        raise JsonProblem(f"no {where}{key!r}")
    return d[key]


def an_object(value: Any, name: str) -> dict:
    """``value`` when it is a JSON object, else JsonProblem."""
    if not isinstance(value, dict):
        raise JsonProblem(f"{name} must be an object, got {shown(value)}")
    return value
