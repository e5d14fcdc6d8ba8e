"""Every code name models_spec/conventions.md cites exists: its dotted names (``geometry.k_params``,
``Rectification.delta_k``) are imported and looked up, its bare names are defined by a module or class of
the runtime or training (or are a test of the suite, or one of the page's data terms), its file paths are
files, and the names its table of homes puts in a file (``geometry/pnp.py`` (``solve_pnp_start``, ...)) are
in that module."""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import re
from pathlib import Path

import pytest

import dimenet.runtime

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "models_spec" / "conventions.md"
RUNTIME_PACKAGES = ("geometry", "rectify", "formats", "sim", "ingest", "evaluation", "cli")
NAME = r"[A-Za-z_][A-Za-z0-9_]*"
DOTTED = re.compile(rf"{NAME}(?:\.{NAME})+")
# Bare words the page uses as data, not as code names: values (a split, scenes, a method, None), stage
# names of the rectifier's timings, the pose variables' names in the code, the package's name.
TERMS = {"None", "test", "natural", "planar", "self", "pnp_kc", "pnp_k", "rvec_c0", "tvec_c0", "dimenet"}


def _cited() -> list[str]:
    """Every backticked text of the page, a call's arguments dropped (``geometry.k_params(K)``)."""
    return [re.sub(r"\(.*\)$", "", text) for text in re.findall(r"`([^`\n]+)`", PAGE.read_text(encoding="utf-8"))]


def _modules(package) -> list:
    """Every module of ``package``, imported."""
    return [importlib.import_module(i.name) for i in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]


def _runtime_classes() -> dict[str, list[type]]:
    """The classes of every dimenet.runtime module, by name."""
    classes: dict[str, list[type]] = {}
    for module in _modules(dimenet.runtime):
        for value in vars(module).values():
            if isinstance(value, type) and value.__module__ == module.__name__:
                classes.setdefault(value.__name__, []).append(value)
    return classes


def _defined_names() -> set[str]:
    """Every name the runtime's and training's modules define or import, their classes' attributes and
    dataclass fields, and the modules' own names."""
    import dimenet.training

    names = set()
    for module in _modules(dimenet.runtime) + _modules(dimenet.training):
        names.add(module.__name__.rsplit(".", 1)[1])
        for name, value in vars(module).items():
            names.add(name)
            if isinstance(value, type):
                names.update(dir(value))
                if dataclasses.is_dataclass(value):
                    names.update(f.name for f in dataclasses.fields(value))
    return names


def _has(owner, name: str) -> bool:
    """``owner`` has attribute ``name``, a dataclass field counted (it need not have a default)."""
    fields = {f.name for f in dataclasses.fields(owner)} if dataclasses.is_dataclass(owner) else set()
    return name in fields or hasattr(owner, name)


def _resolve(dotted: str, classes: dict[str, list[type]]) -> bool:
    """Whether a dotted name exists: a module path below dimenet.runtime (or training, export, cv2) and then
    attributes, or a runtime class and then its attribute."""
    parts = dotted.split(".")
    if parts[0] in classes:
        return any(_has(cls, parts[1]) for cls in classes[parts[0]]) if len(parts) == 2 else False
    if parts[0] in RUNTIME_PACKAGES:
        parts = ["dimenet", "runtime", *parts]
    elif parts[0] in ("training", "export"):
        parts = ["dimenet", *parts]
    elif parts[0] not in ("dimenet", "cv2"):
        return True  # not code of the project's (a file name such as truth.npz)
    for split in range(len(parts), 0, -1):  # the longest importable module, then attributes
        try:
            owner = importlib.import_module(".".join(parts[:split]))
        except ModuleNotFoundError:
            continue
        for name in parts[split:]:
            if not _has(owner, name):
                return False
            owner = getattr(owner, name, None)
        return True
    return False


def _homes() -> list[tuple[str, str]]:
    """(file, name) for each name the table of homes cites in parentheses after a runtime file."""
    pairs = []
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        if not line.startswith("|"):
            continue
        for path, names in re.findall(r"`([a-z_]+/[a-z_]+\.py)` \(([^)]*)\)", line):
            pairs += [(path, name) for name in re.findall(rf"`({NAME})`", names)]
    return pairs


def test_every_dotted_name_the_conventions_cite_exists():
    pytest.importorskip("torch")  # the page cites training.trainer
    classes = _runtime_classes()
    missing = [text for text in _cited() if DOTTED.fullmatch(text) and not _resolve(text, classes)]
    assert missing == []


def test_every_bare_name_the_conventions_cite_is_defined():
    pytest.importorskip("torch")  # the page cites training's names
    defined = _defined_names()
    tests = "\n".join(p.read_text(encoding="utf-8") for p in (ROOT / "tests").rglob("test_*.py"))
    bare = [text for text in _cited() if re.fullmatch(NAME, text) and text not in TERMS]
    assert bare, "the page cites no bare name"
    missing = [
        name
        for name in bare
        if name not in defined and not (name.startswith("test_") and re.search(rf"def {name}\(", tests))
    ]
    assert missing == []


def test_every_file_and_home_the_conventions_cite_exists():
    paths = [text for text in _cited() if text.endswith(".py")]
    assert paths, "the page cites no file"
    missing = [p for p in paths if not ((ROOT / "runtime" / p).is_file() or (ROOT / p).is_file())]
    assert missing == []
    homes = _homes()
    assert homes, "the table of homes names nothing in parentheses"
    absent = []
    for path, name in homes:
        module = importlib.import_module("dimenet.runtime." + path[: -len(".py")].replace("/", "."))
        if not hasattr(module, name):
            absent.append(f"{path}: {name}")
    assert absent == []
