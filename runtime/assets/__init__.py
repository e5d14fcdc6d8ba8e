"""The files the runtime ships: the default model, the example frames and the paper rig."""

from importlib import resources
from importlib.abc import Traversable


def asset(name: str) -> Traversable:
    """The bundled file ``name`` of this folder (it may be missing from a trimmed installation)."""
    return resources.files(__name__) / name
