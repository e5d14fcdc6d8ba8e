"""The layers of the house, held two ways: each package imported alone in a fresh process loads no module
of a higher layer or of a sibling, and the import statements of every module (those inside functions
too, parsed) go only downwards, so packages form no cycle and the runtime never imports training or
export. (tests/rectify/test_import_boundaries.py holds the app's face: the rectifier and torch.)

The order, lowest first; a package imports only from layers below its own:

- ``errors``, the typed errors every layer raises (the root package loads them);
- the runtime's other leaves: ``json_text``, ``assets``, ``plugins`` (entry points by group);
- ``geometry``: pure projection, rotation, PnP starts, least squares;
- ``rectify``: what an app ships, on geometry;
- ``dimenet.runtime`` itself: the package face, which hands out ``Rectifier`` lazily from rectify;
- ``formats`` (the files of models_spec/, some holding a rectify camera) beside ``jobs`` (a function
  over items: the engine, the workers, progress), which import nothing of each other;
- ``sim``, ``ingest`` and ``evaluation``, siblings: the simulator, photos to datasets, measuring;
- ``bench``: the benches, which put the three together (render, ingest, score, time);
- ``cli``: the command line over all of them;
- ``training`` (torch), then ``export`` (which exports a trained model).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {f"dimenet.{name}": ROOT / name for name in ("runtime", "training", "export")}
LAYERS = (
    ("dimenet.runtime.errors",),
    ("dimenet.runtime.json_text", "dimenet.runtime.assets", "dimenet.runtime.plugins"),
    ("dimenet.runtime.geometry",),
    ("dimenet.runtime.native",),
    ("dimenet.runtime.rectify",),
    ("dimenet.runtime",),
    ("dimenet.runtime.formats", "dimenet.runtime.jobs"),
    ("dimenet.runtime.sim", "dimenet.runtime.ingest", "dimenet.runtime.evaluation"),
    ("dimenet.runtime.bench",),
    ("dimenet.runtime.cli",),
    ("dimenet.training",),
    ("dimenet.export",),
)
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}
HEAVY = ("torch", "onnx", "ray")  # third parties no runtime package may load


# `python -m dimenet`'s file: installed as dimenet/__main__.py (pyproject.toml), not a module of runtime.
MODULE_ENTRY = "module_entry"


def modules() -> dict[str, Path]:
    """Every module of the three packages: dotted name -> file."""
    found = {}
    for package, folder in SOURCES.items():
        for path in sorted(folder.rglob("*.py")):
            if MODULE_ENTRY in path.relative_to(folder).parts:
                continue
            parts = path.relative_to(folder).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            found[".".join((package, *parts))] = path
    return found


def unit_of(module: str) -> str:
    """The layer unit (a key of RANK) a module belongs to: its longest prefix among the units."""
    return max((u for u in RANK if module == u or module.startswith(u + ".")), key=len)


def imports(module: str, path: Path, known: set[str]) -> set[str]:
    """The dimenet modules ``module`` imports anywhere in its file (``from X import y``: X.y when that
    is a module, else X)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([node.module] if node.module else []))
            for alias in node.names:
                targets.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base)
    return {t for t in targets if t == "dimenet" or t.startswith("dimenet.")}


def unit_edges() -> dict[tuple[str, str], list[str]]:
    """(importing unit, imported unit) -> the imports behind it ("module -> module"), across units only."""
    known = modules()
    edges: dict[tuple[str, str], list[str]] = {}
    for module, path in known.items():
        for target in imports(module, path, set(known)):
            a, b = unit_of(module), unit_of(target)
            if a != b:
                edges.setdefault((a, b), []).append(f"{module} -> {target}")
    return edges


def test_every_module_belongs_to_a_layer():
    """A new package or top-level runtime module must be placed in LAYERS (the root only holds itself)."""
    unplaced = [m for m in modules() if unit_of(m) == "dimenet.runtime" and m != "dimenet.runtime"]
    assert not unplaced, f"add to LAYERS: {unplaced}"


def test_imports_go_only_down_the_layers():
    wrong = {
        f"{a} (layer {RANK[a]}) imports {b} (layer {RANK[b]})": found
        for (a, b), found in unit_edges().items()
        if RANK[b] >= RANK[a]
    }
    assert not wrong, json.dumps(wrong, indent=1)


def first_cycle(graph: dict[str, set[str]]) -> list[str]:
    """A cycle of ``graph`` (node -> nodes it imports) as its nodes, the first repeated at the end; [] for none."""
    done: set[str] = set()

    def cycle_from(node: str, path: list[str]) -> list[str]:
        if node in path:
            return path[path.index(node) :] + [node]
        if node in done:
            return []
        for nxt in sorted(graph.get(node, ())):
            found = cycle_from(nxt, path + [node])
            if found:
                return found
        done.add(node)
        return []

    return next((c for c in (cycle_from(n, []) for n in sorted(graph)) if c), [])


def test_no_package_level_import_cycle():
    graph: dict[str, set[str]] = {}
    for a, b in unit_edges():
        graph.setdefault(a, set()).add(b)
    assert first_cycle(graph) == []


def test_no_two_modules_import_each_other_even_round_a_circle():
    """Module by module (e.g. export's commands and onnx_export once did, over the opset bounds)."""
    known = modules()
    graph = {m: {t for t in imports(m, path, set(known)) if t in known and t != m} for m, path in known.items()}
    assert first_cycle(graph) == []


def test_the_runtime_never_imports_training_or_export():
    upward = [
        imp
        for (a, b), found in unit_edges().items()
        if a.startswith("dimenet.runtime") and not b.startswith("dimenet.runtime")
        for imp in found
    ]
    assert not upward, upward


CODE = """\
import importlib, json, sys

for name in sys.argv[1:]:
    importlib.import_module(name)
print(json.dumps(sorted(sys.modules)))
"""


@pytest.mark.parametrize("unit", sorted(RANK, key=lambda u: (RANK[u], u)))
def test_a_package_imported_alone_loads_no_higher_layer_nor_a_sibling(unit):
    """Every module of ``unit`` imported in a fresh process; the dimenet modules loaded then (the root
    package, loaded as every module's parent, aside) are of lower layers or of ``unit`` itself."""
    if unit in ("dimenet.training", "dimenet.export"):
        for extra in ("torch", "onnx"):  # the base install has neither: skip, not fail
            pytest.importorskip(extra)
    own = [m for m in modules() if unit_of(m) == unit]
    done = subprocess.run(
        [sys.executable, "-c", CODE, *own], capture_output=True, text=True, timeout=300, check=False, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr
    loaded = json.loads(done.stdout.strip().splitlines()[-1])
    wrong = sorted(
        m
        for m in loaded
        if m.startswith("dimenet.")
        and m in modules()
        and unit_of(m) not in (unit, "dimenet.runtime")
        and RANK[unit_of(m)] >= RANK[unit]
    )
    assert not wrong, f"importing {unit} loaded {wrong}"
    if unit.startswith("dimenet.runtime"):
        heavy = sorted(m for m in loaded if m.split(".")[0] in HEAVY)
        assert not heavy, f"importing {unit} loaded {heavy}"
