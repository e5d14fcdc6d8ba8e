"""JSON text inside dimenet files (a dataset's ``meta``, a rig file): parsed with limits.

``json.loads`` alone raises RecursionError on deeply nested input (``"[" * 100000``) and
ValueError on integers of more than 4300 digits, and it keeps the last of duplicated keys. Here
every such input is a ``JsonProblem`` (a ValueError) the caller turns into its typed error.
"""

from __future__ import annotations

import json
from typing import Any, Optional

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
