"""The C core as plain C (runtime/native): it compiles warning-free as C99 under -Wall -Wextra -pedantic
-Werror, its own driver (tests/native/core_driver.c: every entry point on valid and hostile frames) and
the fuzz target's replay (runtime/native/fuzz: 20 000 pseudo-random inputs) run clean under
AddressSanitizer and UndefinedBehaviorSanitizer, and, where clang has libFuzzer, a short fuzzing run
finds nothing. Skipped only where gcc (clang for the last) is absent."""

from __future__ import annotations

import shutil
import subprocess
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NATIVE = ROOT / "runtime" / "native"
CORE = sorted(NATIVE.glob("dimenet_*.c"))  # the core's C files
STRICT = ["-std=c99", "-Wall", "-Wextra", "-pedantic", "-Werror", "-ffp-contract=off"]
SANITIZE = ["-g", "-O1", "-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer"]
REPLAY_CASES = 20_000
C_FILES = [*CORE, NATIVE / "fuzz" / "fuzz_core.c", NATIVE / "fuzz" / "replay.c", ROOT / "tests/native/core_driver.c"]

needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc is not installed")


def _build(tmp_path: Path, name: str, sources: list, flags: list, compiler: str = "gcc") -> Path:
    out = tmp_path / name
    done = subprocess.run(
        [compiler, *flags, "-I", str(NATIVE), *map(str, sources), "-lm", "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr
    return out


def _run_clean(program: Path, *args: str) -> str:
    done = subprocess.run(
        [str(program), *args],
        capture_output=True,
        text=True,
        timeout=120,
        env={"ASAN_OPTIONS": "abort_on_error=0:detect_leaks=1", "UBSAN_OPTIONS": "print_stacktrace=1"},
    )
    report = done.stdout + done.stderr
    assert done.returncode == 0, report
    assert "runtime error" not in report and "Sanitizer" not in report, report
    return done.stdout


@needs_gcc
@pytest.mark.parametrize("level", ["-O0", "-O3"])
def test_the_core_and_its_c_files_compile_warning_free_as_c99(tmp_path, level):
    for source in C_FILES:
        done = subprocess.run(
            ["gcc", *STRICT, level, "-I", str(NATIVE), "-c", str(source), "-o", str(tmp_path / "x.o")],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 0 and not done.stderr.strip(), (source.name, done.stderr)


@needs_gcc
def test_the_binding_compiles_warning_free_beside_python_s_headers(tmp_path):
    include = sysconfig.get_paths()["include"]
    if not (Path(include) / "Python.h").is_file():
        pytest.skip("the Python headers are not installed")
    binding = sorted(NATIVE.glob("_module*.c"))
    assert len(binding) == 2, binding
    for source in binding:
        done = subprocess.run(
            ["gcc", *STRICT, "-O2", "-fPIC", "-I", str(NATIVE), "-I", include, "-c", str(source)],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
        )
        assert done.returncode == 0 and not done.stderr.strip(), (source.name, done.stderr)


@needs_gcc
def test_the_driver_runs_every_entry_point_clean_under_the_sanitizers(tmp_path):
    driver = _build(tmp_path, "core_driver", [ROOT / "tests/native/core_driver.c", *CORE], [*STRICT, *SANITIZE])
    assert "all checks passed" in _run_clean(driver)


@needs_gcc
def test_the_fuzz_target_replays_pseudo_random_inputs_clean_under_the_sanitizers(tmp_path):
    sources = [NATIVE / "fuzz" / "replay.c", NATIVE / "fuzz" / "fuzz_core.c", *CORE]
    replay = _build(tmp_path, "replay", sources, [*STRICT, *SANITIZE])
    assert f"{REPLAY_CASES} cases" in _run_clean(replay, str(REPLAY_CASES), "49")


@pytest.mark.skipif(shutil.which("clang") is None, reason="clang (libFuzzer) is not installed")
def test_libfuzzer_finds_nothing_in_a_short_run(tmp_path):
    flags = ["-std=c99", "-g", "-O1", "-fsanitize=fuzzer,address,undefined", "-fno-sanitize-recover=all"]
    # An empty program links against libFuzzer's main only where its runtime is installed: the link then
    # fails on the missing LLVMFuzzerTestOneInput, else on the missing library.
    probe = subprocess.run(["clang", *flags, "-x", "c", "-", "-o", str(tmp_path / "probe")], input="", text=True,
                           capture_output=True, timeout=60)  # fmt: skip
    if "LLVMFuzzerTestOneInput" not in probe.stderr:
        pytest.skip("this clang has no libFuzzer runtime")
    fuzzer = _build(tmp_path, "fuzz_core", [NATIVE / "fuzz" / "fuzz_core.c", *CORE], flags, compiler="clang")
    done = subprocess.run(
        [str(fuzzer), "-runs=5000", "-seed=49", f"-artifact_prefix={tmp_path}/", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0 and "Done 5000 runs" in done.stderr, done.stderr[-2000:]
