"""The package as pip builds it (issue 49, "Wheels"): the sdist carries the compiled core's sources,
and where no C compiler works the same sdist still builds a wheel, the pure-numpy one, with one
warning. (pyproject.toml's [tool.cibuildwheel] builds the platform wheels; tests/native is their test.)"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import tarfile
import zipfile
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CORE_SOURCES = (
    "dimenet_core.c",
    "dimenet_features.c",
    "dimenet_pose.c",
    "dimenet_checks.c",
    "dimenet_core.h",
    "dimenet_internal.h",
    "_binding.h",
    "_module.c",
    "_module_pose.c",
)
BUILD = "import sys; from setuptools import build_meta as b; print(getattr(b, sys.argv[1])(sys.argv[2]))"


def _build(kind: str, source: Path, out: Path, env: dict) -> tuple[Path, str]:
    """``build_sdist`` or ``build_wheel`` (setuptools' PEP 517 hooks, as pip calls them) of ``source``
    into ``out``: the file written and the build's stderr."""
    run = subprocess.run(
        [sys.executable, "-c", BUILD, kind, str(out)], cwd=source, env=env, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr[-2000:]
    return out / run.stdout.strip().splitlines()[-1], run.stderr


@pytest.fixture(scope="module")
def sdist(tmp_path_factory) -> Path:
    """The sdist of a copy of the checkout (a build writes egg-info and build/ beside its sources)."""
    pytest.importorskip("setuptools", reason="the build backend is not installed here (CI's floors venv)")
    tmp = tmp_path_factory.mktemp("sdist")
    ignored = shutil.ignore_patterns(".git", "node_modules", "build", "dist", "*.egg-info", "__pycache__", "*.so")
    shutil.copytree(ROOT, tmp / "checkout", ignore=ignored)
    path, _ = _build("build_sdist", tmp / "checkout", tmp, dict(os.environ))
    return path


def test_the_sdist_carries_the_compiled_core_and_its_build(sdist):
    with tarfile.open(sdist) as tar:
        names = {Path(*Path(n).parts[1:]).as_posix() for n in tar.getnames()}
    assert "setup.py" in names and "pyproject.toml" in names
    assert {f"runtime/native/{name}" for name in CORE_SOURCES} <= names


def _builds_wheels() -> bool:
    """This environment's setuptools builds a wheel: itself from 70.1, before that with the wheel package
    (pip's build isolation brings both; a venv made by Python 3.11 holds setuptools 65 alone, CI's floors venv none)."""
    try:
        major, minor = (int(part) for part in version("setuptools").split(".")[:2])
    except PackageNotFoundError:
        return False
    return (major, minor) >= (70, 1) or importlib.util.find_spec("wheel") is not None


@pytest.mark.skipif(not _builds_wheels(), reason="setuptools < 70.1 without the wheel package builds no wheel")
def test_without_a_c_compiler_the_sdist_builds_the_numpy_wheel_with_one_warning(sdist, tmp_path):
    with tarfile.open(sdist) as tar:
        tar.extractall(tmp_path, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    source = next(p for p in tmp_path.iterdir() if p.is_dir())
    env = dict(os.environ, CC="false", LDSHARED="false", CXX="false")
    (tmp_path / "wheel").mkdir()
    wheel, stderr = _build("build_wheel", source, tmp_path / "wheel", env)
    assert stderr.count("dimenet's compiled core was not built") == 1
    assert "the pure-numpy implementation is installed" in stderr
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
    assert "dimenet/runtime/native/__init__.py" in names and "dimenet/runtime/rectify/features.py" in names
    assert not [n for n in names if n.startswith("dimenet/runtime/native/_core")]
