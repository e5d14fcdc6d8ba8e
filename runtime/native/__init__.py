"""Which implementation runs the per-frame kernels: the compiled core or numpy.

The compiled core (``dimenet.runtime.native._core``, built from dimenet_core.c and _module.c beside
this file by ``pip install .``) computes the feature stage of every encoder
(``rectify.features.grid_features``); the numpy code stays the reference and the fallback. The choice
is made once, at import:

- ``DIMENET_IMPLEMENTATION`` unset (or empty): "c" when the extension imports, else "python" (a
  machine without a compiler installs the pure-numpy package);
- ``DIMENET_IMPLEMENTATION=python``: numpy, whatever is built;
- ``DIMENET_IMPLEMENTATION=c``: the compiled core, an ImplementationError when it is not built;
- any other value: an ImplementationError.

``dimenet --version`` and ``dimenet bench`` print the one running. Tests and benchmarks switch it in
process with ``set_implementation`` (or ``using``, its context manager); an app has no reason to.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType
from typing import Optional

from dimenet.runtime.errors import DimenetError

ENV_VARIABLE = "DIMENET_IMPLEMENTATION"
IMPLEMENTATIONS = ("c", "python")


class ImplementationError(DimenetError):
    """DIMENET_IMPLEMENTATION names no implementation, or the compiled core it asks for is not built."""


def _compiled() -> tuple[Optional[ModuleType], Optional[str]]:
    """The extension module, or None and why it does not import."""
    try:
        from dimenet.runtime.native import _core
    except ImportError as exc:
        return None, str(exc)
    return _core, None


def _chosen(asked: Optional[str]) -> tuple[str, Optional[ModuleType]]:
    if asked not in (None, "", *IMPLEMENTATIONS):
        raise ImplementationError(
            f"{ENV_VARIABLE} must be one of {', '.join(IMPLEMENTATIONS)} (or unset: c when it is built), got {asked!r}"
        )
    if asked == "python":
        return "python", None
    module, why = _compiled()
    if module is None and asked == "c":
        raise ImplementationError(
            f"{ENV_VARIABLE}=c but the compiled core is not built ({why}); reinstall with a C compiler "
            f"(pip install . builds it) or set {ENV_VARIABLE}=python"
        )
    return ("c", module) if module is not None else ("python", None)


# The implementation running, and the extension module when it is "c" (None: numpy). Read per call
# by the kernels' callers (rectify.features); only set_implementation changes them.
IMPLEMENTATION, core = _chosen(os.environ.get(ENV_VARIABLE))


def implementation() -> str:
    """The implementation running: "c" or "python"."""
    return IMPLEMENTATION


def compiled_available() -> bool:
    """Whether the compiled core is built (whichever runs)."""
    return _compiled()[0] is not None


def set_implementation(name: str) -> None:
    """Run ``name`` ("c" or "python") from now on, in this process (tests and benchmarks);
    ImplementationError for another name or for "c" when it is not built. Not for use while other
    threads rectify."""
    global IMPLEMENTATION, core
    if name not in IMPLEMENTATIONS:
        raise ImplementationError(f"the implementation must be one of {', '.join(IMPLEMENTATIONS)}, got {name!r}")
    IMPLEMENTATION, core = _chosen(name)


@contextmanager
def using(name: str) -> Iterator[None]:
    """``set_implementation(name)`` inside a with block, the previous one restored after it."""
    previous = IMPLEMENTATION
    set_implementation(name)
    try:
        yield
    finally:
        set_implementation(previous)
