"""An output never replaces an input of the same command (issue 33): every command with an --out
refuses one that is, or resolves to, one of its inputs, in one line before anything runs, and
the input is left as it was. The inputs' contents do not matter: nothing is read first."""

from __future__ import annotations

import os
import stat

import pytest
from helpers import importable

from dimenet.runtime.cli.main import CliError, main
from dimenet.runtime.cli.outputs import refuse_overwriting_inputs

CONTENT = b"precious input\n"


@pytest.fixture
def files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in ("rec.csv", "s8.npz", "cam.json", "rig.json", "photo.jpg", "model.onnx"):
        (tmp_path / name).write_bytes(CONTENT)
    return tmp_path


def refused(capsys, argv, *kept):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "writing it would replace that file" in err[0], err
    for path in kept:
        assert path.read_bytes() == CONTENT, path
    return err[0]


def test_rectify_points_out_is_the_recording(files, capsys):
    line = refused(
        capsys, ["rectify", "--points", "rec.csv", "--camera", "cam.json", "--out", "rec.csv"], files / "rec.csv"
    )
    assert line == (
        "dimenet: error: dimenet rectify: --out rec.csv is the input --points rec.csv: writing it would replace "
        "that file; choose another --out"
    )


@pytest.mark.parametrize("out", ["./rec.csv", "sub/../rec.csv", "link.jsonl", "hard.jsonl", "ABS"])
def test_rectify_out_that_resolves_to_the_recording(files, capsys, out):
    (files / "sub").mkdir()
    (files / "link.jsonl").symlink_to("rec.csv")
    os.link(files / "rec.csv", files / "hard.jsonl")
    out = str(files / "rec.csv") if out == "ABS" else out
    refused(capsys, ["rectify", "--points", "rec.csv", "--camera", "cam.json", "--out", out], files / "rec.csv")
    assert os.path.islink(files / "link.jsonl")


@pytest.mark.parametrize(
    "argv, kept",
    [
        (["rectify", "s8.npz", "--camera", "cam.json", "--out", "s8.npz"], "s8.npz"),
        (["rectify", "--points", "rec.csv", "--camera", "cam.json", "--out", "cam.json"], "cam.json"),
        (["rectify", "--points", "rec.csv", "--camera", "cam.json#1", "--out", "cam.json"], "cam.json"),
        (["rectify", "--points", "rec.csv", "--model", "model.onnx", "--out", "model.onnx"], "model.onnx"),
        (["calibrate", "s8.npz", "--out", "s8.npz"], "s8.npz"),
        (["calibrate", "s8.npz", "--out", "cal.npz", "--camera-out", "s8.npz", "--camera-format", "json"], "s8.npz"),
        (["ingest", "photo.jpg", "--rig", "rig.json", "--out", "rig.json"], "rig.json"),
        (["ingest", "photo.jpg", "--rig", "paper", "--out", "photo.jpg"], "photo.jpg"),
        (["ingest", "photo.jpg", "--rig", "paper", "--camera", "cam.json", "--out", "cam.json"], "cam.json"),
    ],
)
def test_every_command_refuses_an_input_as_its_out(files, capsys, argv, kept):
    refused(capsys, argv, files / kept)


def test_two_outputs_of_one_command_are_refused(files, capsys):
    line = refused(capsys, ["calibrate", "s8.npz", "--out", "a.json", "--camera-out", "a.json"], files / "s8.npz")
    assert "--camera-out a.json is also the output --out a.json" in line
    assert not (files / "a.json").exists()


def test_ingest_report_beside_the_dataset_is_an_output(files, capsys):
    (files / "ds.report.json").write_bytes(CONTENT)
    line = refused(
        capsys, ["ingest", "photo.jpg", "--rig", "ds.report.json", "--out", "ds.npz"], files / "ds.report.json"
    )
    assert "--out's report ds.report.json is the input --rig ds.report.json" in line


def test_render_into_the_folder_of_its_rig(files, capsys):
    (files / "shots").mkdir()
    for name in ("truth.npz", "photo-0001.png"):
        (files / "shots" / name).write_bytes(CONTENT)
        refused(
            capsys,
            [
                "render",
                "--rig",
                f"shots/{name}",
                "--profile",
                "galaxy-s8",
                "--n",
                "2",
                "--format",
                "png",
                "--out",
                "shots",
            ],
            files / "shots" / name,
        )


@pytest.mark.skipif(not importable("torch"), reason="the train extra")
def test_train_export_and_fleet_refuse_their_inputs_as_outputs(files, capsys):
    run = files / "run"
    run.mkdir()
    for name in ("weights.safetensors", "spec.json"):
        (run / name).write_bytes(CONTENT)
    refused(capsys, ["train", "s8.npz", "--out", "run", "--init", "run"], run / "weights.safetensors")
    refused(capsys, ["train", "run/spec.json", "--out", "run"], run / "spec.json")
    (files / "run" / "summary.json").write_bytes(CONTENT)
    refused(capsys, ["fleet", "train", "run/summary.json", "--out", "run"], run / "summary.json")
    if importable("onnx"):
        refused(capsys, ["export", "run", "--out", "run/weights.safetensors"], run / "weights.safetensors")


def test_devices_and_new_files_are_no_clash(tmp_path):
    a = tmp_path / "a.csv"
    a.write_bytes(CONTENT)
    refuse_overwriting_inputs("dimenet x", [("--out", tmp_path / "b.jsonl")], [("--points", a)])
    if hasattr(os, "mknod") and os.geteuid() == 0:
        tty = tmp_path / "tty"
        os.mknod(tty, stat.S_IFCHR | 0o666, os.stat("/dev/null").st_rdev)
        refuse_overwriting_inputs("dimenet x", [("--out", tty)], [("--points", tty)])  # a terminal in and out
    with pytest.raises(CliError, match="is the input"):
        refuse_overwriting_inputs("dimenet x", [("--out", tmp_path / "new.csv")], [("--points", tmp_path / "new.csv")])


def test_a_nul_in_a_path_is_a_usage_error(files, capsys):
    assert main(["rectify", "--points", "rec.csv", "--out", "a\0b"]) == 2
    assert "NUL" in capsys.readouterr().err
