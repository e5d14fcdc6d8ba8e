"""File names an attacker (or an accident) chooses: control characters in a path stay escaped in
the one-line error, and an ASCII-only stdout prints what it cannot encode as escapes, never a
traceback after the file is written (issue 33)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from helpers import example_camera

from dimenet.runtime.bench.streaming import write_points_csv
from dimenet.runtime.cli.main import main, one_line


@pytest.fixture(scope="module")
def recording(tmp_path_factory, frames):
    folder = tmp_path_factory.mktemp("rec")
    write_points_csv(folder / "rec.csv", frames.select(frames.scene == "rig"), 2)
    camera = example_camera()
    (folder / "cam.json").write_text(json.dumps({"K": camera.K.tolist(), "image_size": list(camera.image_size)}))
    return folder


def test_one_line_escapes_c0_c1_del_and_line_separators():
    assert (
        one_line("a\nb\rc\x1b[31md\x85e\x9bf\x7fg\u2028h\x00") == "a\\nb\\rc\\x1b[31md\\x85e\\x9bf\\x7fg\\u2028h\\x00"
    )
    assert one_line("résumé ± σ → ok") == "résumé ± σ → ok"


@pytest.mark.parametrize("name", ["no\nsuch.csv", "red\x1b[31m.csv", "c1\x9b2J.csv", "ls\u2028.csv"])
def test_an_error_naming_a_path_with_control_characters_is_one_escaped_line(recording, capsys, name):
    bad = recording / name
    assert main(["rectify", "--points", str(bad), "--camera", str(recording / "cam.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith("\n")
    assert not any(c in err[:-1] for c in "\n\r\x1b\x9b\u2028"), repr(err)
    assert repr(name)[1:-1] in err


@pytest.mark.skipif(os.name != "posix", reason="a non-ASCII file name on a POSIX file system")
@pytest.mark.parametrize("env", [{"PYTHONIOENCODING": "ascii"}, {"PYTHONIOENCODING": "ascii:strict"}])
def test_an_ascii_only_stdout_prints_escapes_after_writing_the_file(recording, tmp_path, env):
    out = tmp_path / "résumé±.jsonl"
    argv = [
        "rectify",
        "--points",
        str(recording / "rec.csv"),
        "--camera",
        str(recording / "cam.json"),
        "--out",
        str(out),
    ]
    done = subprocess.run(
        [sys.executable, "-m", "dimenet.runtime.cli.main", *argv],
        capture_output=True,
        timeout=300,
        env={**os.environ, **env},
    )
    assert done.returncode == 0 and b"Traceback" not in done.stderr, done.stderr
    assert "r\\xe9sum\\xe9\\xb1.jsonl" in done.stdout.decode("ascii")
    assert out.read_text(encoding="utf-8").startswith('{"format"')
