"""What the installation registers: the entry points of a group by name (pyproject.toml's
``dimenet.commands``, ``dimenet.predictors`` and ``dimenet.benches``), so that the runtime reaches
the training and export packages only through what they register, never by importing them."""

from __future__ import annotations

from importlib import metadata


def entry_points(group: str) -> dict[str, metadata.EntryPoint]:
    """The entry points of ``group``, by name (none: empty)."""
    eps = metadata.entry_points()
    found = eps.select(group=group) if hasattr(eps, "select") else eps.get(group, [])
    return {ep.name: ep for ep in found}
