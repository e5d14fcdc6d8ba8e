"""Points files (models_spec/points-csv.md): CSV and JSON Lines, units, header variants, every
refused case naming its line, lazy reading, and the rectified records (formats.rectified_points, made by
evaluation.rectify_points)."""

from __future__ import annotations

import inspect
import itertools
import json
import os
import threading

import numpy as np
import pytest
from helpers import default_rectifier, random_frames

from dimenet.runtime.errors import DimenetError, PointsError
from dimenet.runtime.evaluation.rectify_points import rectified_records
from dimenet.runtime.formats import points as points_module
from dimenet.runtime.formats.points import read_points
from dimenet.runtime.formats.rectified_points import FORMAT, json_lines, run_record

HEADER = "frame_id,t_ns,x_px,y_px,X_mm,Y_mm,Z_mm"


@pytest.fixture(scope="module")
def scenes():
    """Three frames of 12 points: p2 (3, 12, 2) px, p3 (3, 12, 3) mm."""
    x, X, *_ = random_frames(np.random.default_rng(3), frames=3, points=12)
    return x, X


def _csv_text(x, X, *, header=HEADER, scale=1.0, t=True) -> str:
    rows = [header]
    for b in range(len(x)):
        for p, q in zip(x[b].tolist(), (X[b] / scale).tolist()):
            rows.append(",".join([f"f{b}", *([str(1000 + b)] if t else []), *map(repr, p + q)]))
    return "\n".join(rows) + "\n"


def _write(tmp_path, text, name="rec.csv"):
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


def _read(tmp_path, text, name="rec.csv"):
    return list(read_points(_write(tmp_path, text, name)))


def _check(frames, x, X, t=True, first_lines=(2, 14, 26)):
    assert [f.frame_id for f in frames] == ["f0", "f1", "f2"]
    assert [f.t_ns for f in frames] == ([1000, 1001, 1002] if t else [None] * 3)
    assert [f.line for f in frames] == list(first_lines)
    for f, p, q in zip(frames, x, X):
        assert f.points_2d.dtype == np.float64 and f.points_2d.shape == (12, 2) and f.points_3d.shape == (12, 3)
        np.testing.assert_array_equal(f.points_2d, p)
        np.testing.assert_allclose(f.points_3d, q, rtol=1e-14, atol=1e-12)


def test_csv_frames_in_order_with_their_points_time_and_first_line(tmp_path, scenes):
    text = _csv_text(*scenes)
    frames = _read(tmp_path, text)
    _check(frames, *scenes)
    assert frames[-1].bytes_read == len(text.encode())
    assert frames[0].bytes_read < frames[1].bytes_read < frames[2].bytes_read


def test_metres_give_the_millimetres_points(tmp_path, scenes):
    mm = _read(tmp_path, _csv_text(*scenes), "mm.csv")
    m = _read(tmp_path, _csv_text(*scenes, header=HEADER.replace("_mm", "_m"), scale=1000.0), "m.csv")
    _check(m, *scenes)
    for a, b in zip(mm, m):
        np.testing.assert_allclose(a.points_3d, b.points_3d, rtol=1e-14)
    rectifier = default_rectifier()
    ka = rectifier.rectify(mm[0].points_2d, mm[0].points_3d).K
    kb = rectifier.rectify(m[0].points_2d, m[0].points_3d).K
    np.testing.assert_allclose(ka, kb, rtol=1e-9)


def test_t_ns_is_optional(tmp_path, scenes):
    _check(_read(tmp_path, _csv_text(*scenes, header=HEADER.replace("t_ns,", ""), t=False)), *scenes, t=False)


def test_header_order_spaces_extra_columns_bom_crlf_blank_lines_and_quotes(tmp_path, scenes):
    x, X = scenes
    rows = [" Z_mm , note,x_px,frame_id ,y_px,X_mm,Y_mm,t_ns"]
    for b in range(3):
        for p, q in zip(x[b].tolist(), X[b].tolist()):
            rows.append(f'{q[2]!r},"a, ""quoted"" note",{p[0]!r},f{b},{p[1]!r},{q[0]!r},{q[1]!r},{1000 + b}')
    rows.insert(5, "")  # a blank line inside frame f0 counts as a line, not a point
    text = "\ufeff" + "\r\n".join(rows) + "\r\n"
    frames = _read(tmp_path, text)
    assert [f.line for f in frames] == [2, 15, 27]
    for f, p, q in zip(frames, x, X):
        np.testing.assert_array_equal(f.points_2d, p)
        np.testing.assert_array_equal(f.points_3d, q)


def test_json_lines_give_the_csvs_frames(tmp_path, scenes):
    x, X = scenes
    lines = []
    for b in range(3):
        for p, q in zip(x[b].tolist(), X[b].tolist()):
            d = {"frame_id": f"f{b}", "t_ns": 1000 + b, "x_px": p[0], "y_px": p[1], "note": [1, 2]}
            d.update({"X_m": q[0] / 1000, "Y_m": q[1] / 1000, "Z_m": q[2] / 1000} if b == 1 else {})
            d.update({"X_mm": q[0], "Y_mm": q[1], "Z_mm": q[2]} if b != 1 else {})
            lines.append(json.dumps(d))
    _check(_read(tmp_path, "\n".join(lines) + "\n", "rec.jsonl"), *scenes, first_lines=(1, 13, 25))
    frames = _read(tmp_path, '  \n{"frame_id": 7, "x_px": 1, "y_px": 2, "X_mm": 3, "Y_mm": 4, "Z_mm": 5}\n', "a.txt")
    assert frames[0].frame_id == "7" and frames[0].t_ns is None and frames[0].line == 2  # told by content


GOOD = "a,1,10,20,1,2,3"
CSV_BAD = [
    ("", 1, "no header"),
    ("\n\n", 1, "no header"),
    ("frame_id,x_px,y_px,X_mm,Y_mm\na,1,2,3,4", 1, "it has no Z_mm"),
    ("frame_id,x_px,X_mm,Y_mm,Z_mm\n", 1, "it has no y_px"),
    ("id,x_px,y_px,X_mm,Y_mm,Z_mm\n", 1, "it has no frame_id"),
    ("frame_id,x_px,y_px,X_cm,Y_cm,Z_cm\n", 1, "it has no X_mm, Y_mm, Z_mm"),
    ("frame_id,x_px,y_px,X_mm,Y_mm,Z_mm,X_m,Y_m,Z_m\n", 1, "both X_mm.. and X_m.."),
    ("frame_id,x_px,y_px,X_mm,Y_mm,Z_m\n", 1, "both X_mm.. and X_m.."),
    ("frame_id,x_px,x_px,y_px,X_mm,Y_mm,Z_mm\n", 1, "names x_px twice"),
    (HEADER + "\n", 1, "no points in the file"),
    (HEADER + "\n\n\n", 3, "no points in the file"),
    (HEADER + f"\n{GOOD}\na,1,10,20,1,2\n", 3, "expected 7 fields as the header has, got 6"),
    (HEADER + f"\n{GOOD}\na,1,10,20,1,2,3,4\n", 3, "expected 7 fields"),
    (HEADER + f"\n{GOOD}\na,1,10,abc,1,2,3\n", 3, "y_px must be a number, got 'abc'"),
    (HEADER + f"\n{GOOD}\na,1,10,,1,2,3\n", 3, "y_px must be a number, got ''"),
    (HEADER + f"\n{GOOD}\na,1,10,20,1,nan,3\n", 3, "coordinates must be finite numbers"),
    (HEADER + f"\n{GOOD}\na,1,10,20,1,2,1e400\n", 3, "coordinates must be finite numbers"),
    (HEADER + f"\n{GOOD}\n,1,10,20,1,2,3\n", 3, "empty frame_id"),
    (HEADER + "\na,1.5,10,20,1,2,3\n", 2, "t_ns must be an integer"),
    (HEADER + "\na,,10,20,1,2,3\n", 2, "t_ns must be an integer"),
    (HEADER + f"\na,{2**63},10,20,1,2,3\n", 2, "t_ns must be an integer"),
    (HEADER + f"\n{GOOD}\na,2,10,20,1,2,3\n", 3, "t_ns '2' differs from the frame's first row (1, line 2)"),
    (HEADER + f"\n{GOOD}\na,x,10,20,1,2,3\n", 3, "t_ns must be an integer"),
    (HEADER + f"\n{GOOD}\nb,1,10,20,1,2,3\n{GOOD}\n", 4, "frame_id 'a' reappears after other frames"),
    (HEADER + f"\n{GOOD}\n" + "a" * (70 << 10) + "\n", 3, "longer than 65536 bytes"),
    (HEADER.encode() + b"\na,1,10,20,1,2,\xff\n", 2, "not UTF-8 text"),
    (HEADER + f'\n{GOOD}\na,1,10,20,1,2,"3\n' + ("x" * 60000 + "\n") * 3, 3, "not a readable CSV row"),
]


@pytest.mark.parametrize("text, line, words", CSV_BAD)
def test_every_malformed_csv_is_a_points_error_naming_the_line(tmp_path, text, line, words):
    path = _write(tmp_path, text)
    with pytest.raises(PointsError) as exc:
        list(read_points(path))
    assert isinstance(exc.value, DimenetError) and isinstance(exc.value, ValueError)
    assert str(exc.value).startswith(f"{path}:{line}: ") and words in str(exc.value), str(exc.value)


POINT = '{"frame_id": "a", "t_ns": 1, "x_px": 1, "y_px": 2, "X_mm": 3, "Y_mm": 4, "Z_mm": 5}'
JSONL_BAD = [
    (POINT + "\n{", 2, "not valid JSON"),
    (POINT + "\n[1, 2]", 2, "expected a JSON object"),
    (POINT + '\n{"frame_id": "a", "a": 1, "a": 2}', 2, "not valid JSON (key 'a' appears twice"),
    (POINT + "\n" + POINT.replace('"y_px": 2, ', ""), 2, "it has no y_px"),
    (POINT + "\n" + POINT.replace('"Z_mm"', '"Z_m"'), 2, "both X_mm.. and X_m.."),
    (POINT + "\n" + POINT.replace('"x_px": 1', '"x_px": "1"'), 2, "x_px must be a finite number, got '1'"),
    (POINT + "\n" + POINT.replace('"x_px": 1', '"x_px": true'), 2, "x_px must be a finite number"),
    (POINT + "\n" + POINT.replace('"x_px": 1', '"x_px": 1e400'), 2, "x_px must be a finite number"),
    (POINT.replace('"a"', "true"), 1, "frame_id must be a string or an integer"),
    (POINT.replace('"a"', "1.5"), 1, "frame_id must be a string or an integer"),
    (POINT.replace('"a"', '""'), 1, "empty frame_id"),
    (POINT.replace('"t_ns": 1', '"t_ns": 1.0'), 1, "t_ns must be an integer"),
    (POINT.replace('"t_ns": 1', f'"t_ns": {2**63}'), 1, "t_ns must be an integer"),
    (POINT + "\n" + POINT.replace('"t_ns": 1', '"t_ns": null'), 2, "t_ns None differs"),
    (POINT + "\n" + POINT.replace('"a"', '"b"') + "\n" + POINT, 3, "frame_id 'a' reappears"),
]


@pytest.mark.parametrize("text, line, words", JSONL_BAD)
def test_every_malformed_json_line_is_a_points_error_naming_the_line(tmp_path, text, line, words):
    path = _write(tmp_path, text + "\n", "rec.jsonl")
    with pytest.raises(PointsError) as exc:
        list(read_points(path))
    assert str(exc.value).startswith(f"{path}:{line}: ") and words in str(exc.value), str(exc.value)


def test_an_unreadable_file_and_a_frame_over_the_point_cap(tmp_path, monkeypatch):
    with pytest.raises(PointsError, match="missing.csv: cannot read the points file"):
        next(read_points(tmp_path / "missing.csv"))
    with pytest.raises(PointsError, match="cannot read the points file"):
        next(read_points(tmp_path))
    monkeypatch.setattr(points_module, "MAX_FRAME_POINTS", 3)
    path = _write(tmp_path, HEADER + "\n" + f"{GOOD}\n" * 4)
    with pytest.raises(PointsError, match=rf"{path}:5: frame 'a' has more than 3 points"):
        list(read_points(path))


def test_a_reappearing_frame_id_is_caught_after_thousands_of_frames(tmp_path):
    rows = [f"f{k},0,1,2,3,4,5" for k in range(10_000)]  # the seen ids pass the set into the sorted array
    path = _write(tmp_path, "\n".join([HEADER, *rows, "f17,0,1,2,3,4,5"]) + "\n")
    frames = read_points(path)
    assert sum(1 for _ in zip(range(10_000), frames)) == 10_000
    with pytest.raises(PointsError, match=rf"{path}:10002: frame_id 'f17' reappears"):
        next(frames)


def test_the_reader_is_lazy_on_an_endless_stream(tmp_path):
    """A FIFO fed without end: the first frames come out, and closing the reader ends the feed
    (the file is never read whole, so memory stays that of a frame)."""
    fifo = tmp_path / "endless.csv"
    os.mkfifo(fifo)

    def feed():
        try:
            with open(fifo, "w") as f:
                f.write(HEADER + "\n")
                for k in itertools.count():
                    f.write("".join(f"f{k},{k},{i},2,3,4,5\n" for i in range(8)))
        except BrokenPipeError:  # the reader is gone
            pass

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    frames = read_points(fifo)
    assert inspect.isgenerator(frames)
    first = [next(frames) for _ in range(3)]
    assert [f.frame_id for f in first] == ["f0", "f1", "f2"] and [f.t_ns for f in first] == [0, 1, 2]
    assert all(f.points_2d.shape == (8, 2) for f in first)
    frames.close()
    writer.join(timeout=10)
    assert not writer.is_alive()


def test_records_a_refused_frame_is_an_error_line_and_the_run_goes_on(tmp_path, scenes):
    x, X = scenes
    text = _csv_text(x, X)
    lines = text.splitlines()  # the header, then 12 rows per frame
    path = _write(tmp_path, "\n".join(lines[:13] + lines[13:16] + lines[25:]) + "\n")
    frames = list(read_points(path))
    assert [len(f.points_2d) for f in frames] == [12, 3, 12]
    rectifier = default_rectifier()
    records = list(rectified_records(rectifier, frames, refine=False))
    assert records[1] == {"frame_id": "f1", "t_ns": 1001, "error": "3 points: rectification needs at least 6"}
    for record, frame in zip(records[::2], frames[::2]):
        res = rectifier.rectify(frame.points_2d, frame.points_3d)
        assert "error" not in record and record["frame_id"] == frame.frame_id and record["t_ns"] == frame.t_ns
        np.testing.assert_array_equal(record["K"], res.K)
        np.testing.assert_array_equal(record["rvec"], res.rvec)
        assert record["e_px"] == res.reprojection_error_px and record["fallback"] == res.fallback
        if res.K_cov is None:
            assert record["K_sigma_px"] is None
        else:
            np.testing.assert_array_equal(record["K_sigma_px"], np.sqrt(np.diag(res.K_cov)))
    out = list(json_lines(run_record(rectifier, refine=False, points=str(path), camera=None), iter(records)))
    header = json.loads(out[0])
    assert header["format"] == FORMAT and header["K_c"] == rectifier.K_c.tolist()
    assert header["image_size"] == list(rectifier.image_size) and header["model_sha256"] == rectifier.model.sha256
    assert [json.loads(line) for line in out[1:]] == records and all(line.endswith("\n") for line in out)
