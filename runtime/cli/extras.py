"""What each command needs beyond the base install, by command and by its arguments: the one table
(``NEEDS``) that every missing-extra message reads.

The base install (numpy, opencv-python-headless, onnxruntime, pyyaml) runs every command with every
argument but those the table names. Before a command runs, ``missing_extras`` looks for the modules of
the extras its arguments need (without importing them) and, when one is absent, names the one install
that makes the command work: ``pip install 'dimenet-runtime[EXTRA]'`` (``.[EXTRA]`` in a checkout), with
the CPU build of torch first where torch is missing (a plain ``pip install torch`` may pull a CUDA build
of several GB). tests/cli/test_extras.py holds ``EXTRAS`` to pyproject.toml's optional dependencies
and every command's message to this table.
"""

from __future__ import annotations

import argparse
import importlib.util
from dataclasses import dataclass
from typing import Callable, Optional

from dimenet.runtime.rectify.model import resolve_model

# pyproject.toml's extras, each by the modules it brings (the dev extra's are no command's).
EXTRAS = {
    "train": ("torch", "safetensors", "matplotlib", "onnx"),
    "export": ("onnx",),
    "fleet": ("ray",),
}
CPU_TORCH = "pip install torch --index-url https://download.pytorch.org/whl/cpu"
DISTRIBUTION = "dimenet-runtime"


@dataclass(frozen=True)
class Need:
    """A command needs ``extra`` when ``applies(args)``; ``when`` names those arguments in the message
    ('' for a command that always needs it)."""

    extra: str
    when: str = ""
    applies: Callable[[argparse.Namespace], bool] = lambda args: True


def _address(args: argparse.Namespace) -> bool:
    return args.address is not None


def _run_dir(path: Optional[str]) -> bool:
    """A RUN_DIR of `dimenet train` (torch loads it); a bundled model's name or a model file needs no torch."""
    return path is not None and resolve_model(path).run_dir


# command -> what it needs beyond the base install, and when. A command not named needs nothing more.
NEEDS: dict[str, tuple[Need, ...]] = {
    "train": (Need("train"),),
    "reproduce": (Need("train"), Need("fleet", "--address", _address)),
    "fleet": (Need("train"), Need("fleet", "--address", _address)),
    "simulate": (Need("fleet", "--address", _address),),
    "evaluate": (Need("train", "--model RUN_DIR", lambda a: _run_dir(a.model)),),
    "bench": (Need("train", "--bpnp", lambda a: a.bpnp),),
    "export": (
        Need("train", "RUN_DIR", lambda a: a.golden is None and _run_dir(a.source)),
        # The ORT converter sits beside the torch export (export/onnx_export.py), which it imports.
        Need("train", "--format ort", lambda a: a.golden is None and a.format == "ort"),
        Need("export", "--graph full", lambda a: a.golden is None and a.graph == "full"),
    ),
}


def _absent(module: str) -> bool:
    return importlib.util.find_spec(module) is None


def install_command(extras: tuple[str, ...]) -> str:
    """The one install that brings ``extras``: the CPU build of torch first when torch is one of their
    modules and is missing."""
    names = ",".join(extras)
    torch_first = f"{CPU_TORCH}, then " if any(m == "torch" and _absent(m) for e in extras for m in EXTRAS[e]) else ""
    return f"{torch_first}pip install '{DISTRIBUTION}[{names}]' (in a checkout: pip install '.[{names}]')"


def missing_extras(command: str, args: argparse.Namespace) -> Optional[str]:
    """None when every module ``command`` needs with ``args`` is installed; else one line naming the
    missing modules, their extras and the one install that brings them."""
    needs = [n for n in NEEDS.get(command, ()) if n.applies(args)]
    short = [n for n in needs if any(_absent(m) for m in EXTRAS[n.extra])]
    if not short:
        return None
    extras = tuple(dict.fromkeys(n.extra for n in short))
    # An extra whose modules another one already brings adds nothing to the install (train brings onnx).
    extras = tuple(e for e in extras if not any(o != e and set(EXTRAS[e]) <= set(EXTRAS[o]) for o in extras))
    modules = [m for e in extras for m in EXTRAS[e] if _absent(m)]
    when = " ".join(dict.fromkeys(n.when for n in short if n.when))
    which = " and ".join(f"the {e} extra" for e in extras)
    return (
        f"dimenet {command}{' ' + when if when else ''} needs {', '.join(dict.fromkeys(modules))} ({which}): "
        f"{install_command(extras)}"
    )
