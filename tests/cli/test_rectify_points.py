"""`dimenet rectify --points` end to end (stdout, --out, a shell pipe, a bad file), the camera and
model in dataset mode's RESULT.npz, and `dimenet bench --stream`."""

from __future__ import annotations

import io
import json
import shlex
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest
from helpers import DEVICE_MODEL, default_rectifier, example_camera

from dimenet.runtime.bench.streaming import write_points_csv
from dimenet.runtime.cli.commands import rectify as rectify_command
from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.points import read_points
from dimenet.runtime.formats.rectified_points import FORMAT


@pytest.fixture(scope="module")
def camera_file(tmp_path_factory):
    camera = example_camera()
    path = tmp_path_factory.mktemp("camera") / "cam.json"
    path.write_text(json.dumps({"K": camera.K.tolist(), "image_size": list(camera.image_size)}))
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory, frames):
    """A points CSV of 6 simulated galaxy-s8 frames (the rig frames of the session's set)."""
    path = tmp_path_factory.mktemp("points") / "rec.csv"
    write_points_csv(path, frames.select(frames.scene == "rig"), 6)
    return path


def _lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines()]


def test_each_line_is_rectify_on_the_frames_points(recording, camera_file, capsys):
    assert main(["rectify", "--points", str(recording), "--camera", str(camera_file)]) == 0
    out = capsys.readouterr()
    header, *records = _lines(out.out)
    rectifier = default_rectifier()
    assert header["format"] == FORMAT and header["mode"] == "dimenet" and header["refine"] is False
    assert header["K_c"] == rectifier.K_c.tolist() and header["image_size"] == [4032, 3024]
    assert header["model_sha256"] == rectifier.model.sha256 and header["camera"] == str(camera_file)
    frames = list(read_points(recording))
    assert [r["frame_id"] for r in records] == [f"f{k}" for k in range(6)] and len(frames) == 6
    for record, frame in zip(records, frames):
        res = rectifier.rectify(frame.points_2d, frame.points_3d)
        assert record["t_ns"] == frame.t_ns and record["fallback"] == res.fallback
        assert record["fallback_code"] == res.fallback_code
        np.testing.assert_array_equal(record["K"], res.K)
        np.testing.assert_array_equal(record["tvec"], res.tvec)
        assert record["e_px"] == res.reprojection_error_px and record["e_c_px"] == res.reprojection_error_kc_px
        np.testing.assert_array_equal(record["K_sigma_px"], np.sqrt(np.diag(res.K_cov)))
    assert out.err == ""  # no bar: stderr is not a terminal


def test_out_writes_the_same_lines_atomically_and_a_refused_frame_is_a_line(recording, camera_file, tmp_path, capsys):
    lines = recording.read_text().splitlines()
    short = tmp_path / "short.csv"  # frame f1 keeps 4 of its points
    f1 = [i for i, line in enumerate(lines) if line.startswith("f1,")]
    short.write_text("\n".join(lines[: f1[0] + 4] + lines[f1[-1] + 1 :]) + "\n")
    out = tmp_path / "rec.jsonl"
    assert main(["rectify", "--points", str(short), "--camera", str(camera_file), "--out", str(out)]) == 0
    assert capsys.readouterr().out == f"6 frames (1 refused, 0 fallbacks) -> {out}\n"
    header, *records = _lines(out.read_text())
    assert records[1] == {"frame_id": "f1", "t_ns": 33_333_333, "error": "4 points: rectification needs at least 6"}
    assert all("K" in r for r in records[:1] + records[2:])
    assert main(["rectify", "--points", str(short), "--camera", str(camera_file)]) == 0
    assert _lines(capsys.readouterr().out)[1:] == records


def test_a_recording_of_which_no_frame_is_rectified_exits_1(recording, camera_file, tmp_path, capsys):
    lines = recording.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    kept, seen = [], Counter()
    for row in rows:  # every frame keeps 4 of its points: each is refused
        seen[row.split(",")[0]] += 1
        if seen[row.split(",")[0]] <= 4:
            kept.append(row)
    few = tmp_path / "few.csv"
    few.write_text("\n".join([header, *kept]) + "\n")
    out = tmp_path / "few.jsonl"
    assert main(["rectify", "--points", str(few), "--camera", str(camera_file), "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert captured.out == f"6 frames (6 refused, 0 fallbacks) -> {out}\n"
    assert captured.err == f"dimenet: {few}: no frame was rectified (6 of 6 refused; each record's error says why)\n"
    assert all("error" in r for r in _lines(out.read_text())[1:])
    assert main(["rectify", "--points", str(few), "--camera", str(camera_file)]) == 1
    assert len(_lines(capsys.readouterr().out)) == 7


@pytest.mark.parametrize(
    "args, words",
    [
        (["--json"], "--json applies to a dataset"),
        (["--example"], "give a dataset file, --example or --points FILE"),
        (["data.npz"], "give a dataset file, --example or --points FILE"),
    ],
)
def test_points_refuses_the_dataset_options(recording, camera_file, capsys, args, words):
    assert main(["rectify", "--points", str(recording), "--camera", str(camera_file), *args]) == 2
    assert words in capsys.readouterr().err


def test_a_generic_model_needs_the_camera_a_device_model_has_its_own(recording, capsys):
    assert main(["rectify", "--points", str(recording)]) == 2
    assert "is a generic model: it needs your camera" in capsys.readouterr().err
    assert main(["rectify", "--points", str(recording), "--model", str(DEVICE_MODEL)]) == 0
    header, *records = _lines(capsys.readouterr().out)
    assert header["camera"] is None and header["model"] == str(DEVICE_MODEL) and header["image_size"] == [4032, 3024]
    assert len(records) == 6 and all("K" in r for r in records)


def _format_2(recording, tmp_path, shift_px: float):
    """The recording as points format 2: frame k's own K_c the example camera's with c moved by k * shift_px."""
    K = example_camera().K
    lines = recording.read_text().splitlines()
    out = ["#dimenet-points/2", lines[0] + ",fx_px,fy_px,cx_px,cy_px"]
    for line in lines[1:]:
        k = int(line.split(",", 1)[0][1:])
        k_c = (K[0, 0], K[1, 1], K[0, 2] + k * shift_px, K[1, 2] - k * shift_px)
        out.append(line + "," + ",".join(repr(float(v)) for v in k_c))
    path = tmp_path / "rec2.csv"
    path.write_text("\n".join(out) + "\n")
    return path


def test_a_format_2_file_rectifies_each_frame_about_its_own_k_c(recording, camera_file, tmp_path, capsys):
    path = _format_2(recording, tmp_path, 4.0)
    assert main(["rectify", "--points", str(path), "--camera", str(camera_file)]) == 0
    _, *records = _lines(capsys.readouterr().out)
    rectifier = default_rectifier()
    frames = list(read_points(path))
    assert len(records) == len(frames) == 6
    for record, frame in zip(records, frames):
        res = rectifier.rectify(frame.points_2d, frame.points_3d, K_c=frame.K_c)
        np.testing.assert_array_equal(record["K_c"], frame.K_c)
        np.testing.assert_array_equal(record["K"], res.K)
        assert record["e_c_px"] == res.reprojection_error_kc_px and record["fallback_code"] == res.fallback_code
    assert records[3]["K_c"][0][2] == example_camera().K[0, 2] + 12.0


def _refused_with_motion(points, camera_file, tmp_path, capsys) -> str:
    """The one line of `dimenet rectify --points POINTS --temporal --motion` (a still gyroscope) exiting 2."""
    motion = tmp_path / "gyro.csv"
    motion.write_text("t_ns,gx_rad_s,gy_rad_s,gz_rad_s\n0,0,0,0\n1000000000,0,0,0\n")
    args = ["rectify", "--points", str(points), "--camera", str(camera_file), "--temporal", "--motion", str(motion)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    return err


def test_temporal_tracks_a_format_2_file_about_each_frames_k_c(recording, camera_file, tmp_path, capsys):
    path = _format_2(recording, tmp_path, 4.0)
    assert main(["rectify", "--points", str(path), "--camera", str(camera_file), "--temporal"]) == 0
    _, *records = _lines(capsys.readouterr().out)
    stream = default_rectifier().stream()
    for record, frame in zip(records, read_points(path)):
        out = stream.update(frame.points_2d, frame.points_3d, frame.t_ns, K_c=frame.K_c)
        np.testing.assert_array_equal(record["K_c"], frame.K_c)
        np.testing.assert_array_equal(record["K"], out.result.K)
        assert record["fused"] == out.fused and record["event"] == out.event
    err = _refused_with_motion(path, camera_file, tmp_path, capsys)
    assert "gives its own K_c" in err and "without --motion" in err


def test_temporal_with_motion_refuses_a_file_without_t_ns_with_one_line(recording, camera_file, tmp_path, capsys):
    """Without t_ns the motion cannot be placed: exit 2 naming the frame, not a refused record for every frame."""
    lines = recording.read_text().splitlines()
    t_column = lines[0].split(",").index("t_ns")
    untimed = tmp_path / "untimed.csv"
    untimed.write_text("\n".join(",".join(c for j, c in enumerate(r.split(",")) if j != t_column) for r in lines))
    err = _refused_with_motion(untimed, camera_file, tmp_path, capsys)
    assert "(line 2) has no t_ns" in err and "a t_ns column" in err
    args = ["rectify", "--points", str(untimed), "--camera", str(camera_file), "--temporal"]
    assert main(args) == 0  # without the motion, a file without t_ns streams (one frame time apart)


def _dimenet(command: str) -> subprocess.CompletedProcess:
    """``dimenet`` in a shell command line, with bash's pipefail: a pipe's status is dimenet's."""
    cli = f"{shlex.quote(sys.executable)} -m dimenet.runtime.cli.main"
    return subprocess.run(
        ["bash", "-o", "pipefail", "-c", command.replace("dimenet", cli, 1)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_a_pipe_closed_early_exits_0_quietly(frames, camera_file, tmp_path):
    big = tmp_path / "big.csv"  # 400 frames: ~400 KB of output, far more than a pipe holds
    write_points_csv(big, frames.select(frames.scene == "rig"), 400)
    done = _dimenet(f"dimenet rectify --points {big} --camera {camera_file} | head -1")
    assert done.returncode == 0 and done.stderr == "", done.stderr
    assert json.loads(done.stdout)["format"] == FORMAT and done.stdout.count("\n") == 1


def test_a_malformed_file_exits_2_with_one_line_naming_file_and_line(camera_file, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("frame_id,x_px,y_px,X_mm,Y_mm,Z_mm\na,1,2,3,4,5\na,1,two,3,4,5\n")
    done = _dimenet(f"dimenet rectify --points {bad} --camera {camera_file}")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == f"dimenet: error: {bad}:3: y_px must be a number, got 'two'\n"


def test_dataset_results_name_their_camera_and_model(tmp_path, capsys):
    out = tmp_path / "result.npz"
    assert main(["rectify", "--example", "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    with np.load(out, allow_pickle=False) as npz:
        assert npz["K_c"].shape == (3, 3) and npz["image_size"].tolist() == report["image_size"]
        assert str(npz["model_sha256"]) == report["model_sha256"] and npz["model_sha256"].dtype.kind == "U"
        np.testing.assert_array_equal(npz["K_c"], example_camera().K)


def test_bench_stream_reports_frames_per_second_and_memory(capsys):
    assert main(["bench", "--stream", "30", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["frames"] == 30 and figures["refused"] == 0 and figures["frames_per_s"] > 0
    assert 0 < figures["peak_rss_mb_at_10_percent"] <= figures["peak_rss_mb"]
    assert main(["bench", "--stream", "30", "--points", "20"]) == 2
    assert "--points applies only to" in capsys.readouterr().err


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_on_a_terminal_the_bar_counts_the_blocks_of_the_file_read(recording, camera_file, monkeypatch, capsys):
    monkeypatch.setattr(rectify_command, "PROGRESS_BLOCK", 10_000)
    monkeypatch.setattr(sys, "stderr", _Terminal())
    assert main(["rectify", "--points", str(recording), "--camera", str(camera_file)]) == 0
    total = recording.stat().st_size // 10_000 + 1
    draws = sys.stderr.getvalue().split("\r")[1:]
    assert len(draws) == total and draws[-1].startswith(f"rectify, MiB read [{'#' * 24}] {total}/{total} ")
    assert len(_lines(capsys.readouterr().out)) == 7  # the run record and every frame
