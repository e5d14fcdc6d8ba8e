"""The `dimenet` command line as a user meets it: help with examples, one-line errors, JSON."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from dimenet.runtime.cli.main import build_parser, main
from dimenet.runtime.evaluation.methods import evaluate
from dimenet.runtime.formats.dataset import read_dataset, write_dataset

COMMANDS = [
    "simulate",
    "calibrate",
    "evaluate",
    "train",
    "reproduce",
    "export",
    "rectify",
    "bench",
    "render",
    "ingest",
    "samples",
]


def dimenet(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", "import sys; from dimenet.runtime.cli.main import main; sys.exit(main())", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_every_command_is_registered_and_its_help_has_an_example(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(COMMANDS) <= set(sub.choices)
    for name in COMMANDS:
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        out = capsys.readouterr().out
        assert "example:" in out and f"dimenet {name}" in out


def _examples(text: str) -> list:
    """The command lines of a --help's example section (each line after "example:" or "examples:")."""
    lines = text.split("example", 1)[1].splitlines()[1:]
    return [line.strip() for line in lines if line.strip().startswith("dimenet ")]


def test_every_help_example_is_a_line_bash_parses(capsys):
    """Each example pastes into bash: `bash -n` (parse only) accepts it, comments included."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    texts = [parser.format_help()] + [sub.choices[name].format_help() for name in sorted(sub.choices)]
    examples = [line for text in texts for line in _examples(text)]
    assert len(examples) >= len(sub.choices) + 2
    for line in examples:
        res = subprocess.run(["bash", "-n", "-c", line], capture_output=True, text=True, timeout=30)
        assert res.returncode == 0, (line, res.stderr)
    bad = subprocess.run(["bash", "-n", "-c", "dimenet train x --out y   (a comment)"], capture_output=True, timeout=30)
    assert bad.returncode != 0  # the check itself catches the old style


def test_dimenet_dash_v_shows_the_version():
    shown = dimenet("-V")
    assert shown.returncode == 0 and shown.stdout.startswith("dimenet ")


@pytest.mark.parametrize(
    "args, words",
    [
        (["evaluate", "missing.npz"], "no such dataset file"),
        (["simulate", "--profile", "nokia-3310", "--out", "x.npz"], "nokia-3310"),
        (["evaluate", "missing.npz", "--noise-2d", "-1"], "--noise-2d"),
        (["frobnicate"], "invalid choice"),
        (["calibrate"], "required"),
    ],
)
def test_bad_input_exits_2_with_one_line_and_no_traceback(args, words):
    res = dimenet(*args)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in res.stderr


def test_non_conforming_dataset_is_named(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, format=np.array("something-else"))
    res = dimenet("evaluate", str(bad))
    assert res.returncode == 2 and "bad.npz" in res.stderr and "missing required key" in res.stderr


def test_simulate_calibrate_evaluate_json(tmp_path, s8_dataset, s8_calibration):

    data = write_dataset(s8_dataset, tmp_path / "s8.npz")
    assert main(["calibrate", str(data), "--out", str(tmp_path / "cal.npz")]) == 0
    with np.load(tmp_path / "cal.npz", allow_pickle=False) as cal:
        np.testing.assert_allclose(cal["K_c"], s8_calibration.K_c, atol=1e-9)
        assert cal["K_star"].shape == (s8_dataset.n_frames, 3, 3)
    res = dimenet("evaluate", str(data), "--json")
    assert res.returncode == 0
    report = json.loads(res.stdout)
    rig = report["scenes"]["rig"]
    assert report["split"] == "test" and rig["n_frames"] == 47 and rig["avg_e"] is None and rig["rho"] is None
    test = s8_dataset.select(s8_dataset.frames_in("test"))
    ev = evaluate(test, s8_calibration.K_c)
    assert rig["avg_e_c"] == pytest.approx(ev.scenes["rig"].avg_e_c, rel=1e-9)
    assert set(report["scenes"]) == {"rig", "natural"} and "overall" in report


def test_ingest_bad_input_exits_2_with_one_line(tmp_path):
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    bad_rig = tmp_path / "rig.json"
    bad_rig.write_text('{"format": "dimenet-rig/1", "units": "cm", "boards": []}')
    obj, labels = tmp_path / "object.csv", tmp_path / "labels.csv"
    obj.write_text("point_id,X_mm,Y_mm,Z_mm\np0,1,2,3\n")
    labels.write_text("image,point_id,x_px,y_px\nbroken.jpg,p7,1,2\n")
    out = str(tmp_path / "d.npz")
    for args, words in [
        ([str(broken), "--rig", "paper", "--out", out], "no photo gave a frame"),
        ([str(broken), "--rig", str(bad_rig), "--out", out], "rig.json: units"),
        ([str(tmp_path / "missing.jpg"), "--rig", "paper", "--out", out], "missing.jpg: no such photo"),
        ([str(broken), "--rig", "paper", "--out", out, "--labels", str(labels)], "--labels and --object go together"),
        (
            [str(broken), "--rig", "paper", "--out", out, "--labels", str(labels), "--object", str(obj)],
            "labels.csv:2: point_id 'p7' is not in the object file",
        ),
    ]:
        res = dimenet("ingest", *args)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and words in lines[0] and "Traceback" not in res.stderr, (
            res.stderr
        )
    report = json.loads((tmp_path / "d.report.json").read_text())
    assert "broken.jpg: cannot decode" in report["photos"][0]["skipped"]


def test_cli_simulate_writes_a_dataset(tmp_path, capsys):
    out = tmp_path / "ipad.npz"
    assert (
        main(
            [
                "simulate",
                "--profile",
                "ipad-mini-6",
                "--seed",
                "4",
                "--natural-frames",
                "2",
                "--planar-frames",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    line = capsys.readouterr().out.strip()
    assert "224 train + 57 test rig frames, 2 natural and 1 planar test frames" in line and str(out) in line
    ds = read_dataset(out)
    assert ds.meta["seed"] == 4 and ds.n_frames == 224 + 57 + 2 + 1
    assert main(["simulate", "--profile", "pixel-9", "--out", str(out)]) == 2
    assert main(["simulate", "--profile", "ipad-mini-6", "--natural-frames", "-3", "--out", str(out)]) == 2
    assert "natural-frames" in capsys.readouterr().err


def test_the_version_has_one_source_and_dimenet_version_shows_it():
    """pyproject.toml holds the version; dimenet.runtime reads it from the installed distribution and keeps
    no copy of its own, and ``dimenet --version`` shows it."""
    import re
    from importlib import metadata
    from pathlib import Path

    from dimenet import runtime

    root = Path(__file__).resolve().parents[2]
    declared = re.search(r'^version = "([^"]+)"', (root / "pyproject.toml").read_text(), re.M).group(1)
    assert "__version__ =" not in (root / "runtime" / "__init__.py").read_text()
    assert runtime.__version__ == metadata.version("dimenet-runtime") == declared
    shown = dimenet("--version")
    from dimenet.runtime.native import implementation

    assert shown.returncode == 0 and shown.stdout.strip() == f"dimenet {declared} (implementation {implementation()})"


def test_the_changelog_and_citation_name_the_version_and_the_licence_is_there():
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    declared = re.search(r'^version = "([^"]+)"', (root / "pyproject.toml").read_text(), re.M).group(1)
    newest = re.search(r"^## (\S+)", (root / "CHANGELOG.md").read_text(), re.M).group(1)
    cited = re.search(r'^version: "([^"]+)"', (root / "CITATION.cff").read_text(), re.M).group(1)
    assert newest == cited == declared
    assert (root / "LICENSE").read_text().startswith("MIT License")
    assert 'license = { text = "MIT" }' in (root / "pyproject.toml").read_text()
