"""Points format 2 (models_spec/points-csv.md, "Format 2: a K_c per frame"): the declaration line, the frame's
own K_c in fx_px..cy_px (CSV and JSON Lines), format 1's meaning kept for the same columns, and every refused
case naming its line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dimenet.runtime.errors import PointsError
from dimenet.runtime.formats.points import read_points

HEADER = "frame_id,t_ns,x_px,y_px,X_mm,Y_mm,Z_mm,fx_px,fy_px,cx_px,cy_px"
K_ROW = "3000,3010,2016.5,1512.25"


def _rows(frame: str, k: str, n: int = 3) -> list[str]:
    return [f"{frame},7,{10 + i},{20 + i},{i},{2 * i},0,{k}" for i in range(n)]


def _read(tmp_path, text: str, name: str = "rec.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path, list(read_points(path))


def _K(fx, fy, cx, cy):
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def test_a_declared_csv_gives_each_frame_its_own_k_c(tmp_path):
    text = "\n".join(["#dimenet-points/2", HEADER, *_rows("a", K_ROW), *_rows("b", "2990,3000,2020,1500")]) + "\n"
    _, frames = _read(tmp_path, text)
    assert [f.frame_id for f in frames] == ["a", "b"] and [f.line for f in frames] == [3, 6]
    np.testing.assert_array_equal(frames[0].K_c, _K(3000, 3010, 2016.5, 1512.25))
    np.testing.assert_array_equal(frames[1].K_c, _K(2990, 3000, 2020, 1500))
    assert frames[0].K_c.dtype == np.float64 and frames[0].points_2d.shape == (3, 2)


def test_format_2_without_the_k_columns_and_format_1_with_them_give_no_k_c(tmp_path):
    plain = HEADER.rsplit(",fx_px", 1)[0]
    rows = [r.rsplit(",", 4)[0] for r in _rows("a", K_ROW)]
    _, declared = _read(tmp_path, "\n".join(["#dimenet-points/2", plain, *rows]) + "\n")
    _, format_1 = _read(tmp_path, "\n".join([HEADER, *_rows("a", K_ROW)]) + "\n")  # no declaration: ignored columns
    assert declared[0].K_c is None and format_1[0].K_c is None
    np.testing.assert_array_equal(declared[0].points_3d, format_1[0].points_3d)


def test_a_declared_json_lines_file_gives_k_c_to_the_frames_that_carry_it(tmp_path):
    point = {"frame_id": "a", "x_px": 1, "y_px": 2, "X_m": 0.001, "Y_m": 0, "Z_m": 0}
    k = {"fx_px": 3000, "fy_px": 3010, "cx_px": 2016.5, "cy_px": 1512.25}
    lines = [{"format": "dimenet-points/2"}, {**point, **k}, {**point, **k}, {**point, "frame_id": "b"}]
    _, frames = _read(tmp_path, "\n".join(map(json.dumps, lines)) + "\n", "rec.jsonl")
    np.testing.assert_array_equal(frames[0].K_c, _K(3000, 3010, 2016.5, 1512.25))
    assert frames[1].K_c is None and frames[0].points_3d[0, 0] == 1.0 and frames[0].line == 2
    _, format_1 = _read(tmp_path, json.dumps({**point, **k}) + "\n", "one.jsonl")
    assert format_1[0].K_c is None


BAD = [
    ("#dimenet-points/3\n" + HEADER, 1, "dimenet-points/3 is not a format this release reads"),
    ("#dimenet-pts/2\n" + HEADER, 1, "expected dimenet-points/N"),
    ("#dimenet-points/two\n" + HEADER, 1, "expected dimenet-points/N"),
    ("#dimenet-points/\u00b2\n" + HEADER, 1, "expected dimenet-points/N"),  # isdigit() but not int(): a ValueError
    ("#dimenet-points/" + "1" * 5000 + "\n" + HEADER, 1, "expected dimenet-points/N"),  # past int()'s 4300 digits
    ("#dimenet-points/\u0662\n" + HEADER, 1, "expected dimenet-points/N"),  # an Arabic-Indic 2: int() reads 2
    ("#dimenet-points/2\n" + HEADER.replace(",cy_px", ""), 2, "but not cy_px: a frame's K_c needs all four"),
    ("#dimenet-points/2\n" + HEADER + "\n" + _rows("a", K_ROW)[0] + "\n" + _rows("a", "3000,3010,2016.5,1512")[1], 4,
     "differ from the frame's first row (line 3)"),
    ("#dimenet-points/2\n" + HEADER + "\n" + _rows("a", "3000,nan,2016,1512")[0], 3, "must be finite numbers"),
    ("#dimenet-points/2\n" + HEADER + "\n" + _rows("a", "3000,x,2016,1512")[0], 3, "fy_px must be a number, got 'x'"),
]  # fmt: skip


@pytest.mark.parametrize("text, line, words", BAD)
def test_every_malformed_format_2_csv_is_a_points_error_naming_the_line(tmp_path, text, line, words):
    path = tmp_path / "rec.csv"
    path.write_text(text + "\n", encoding="utf-8")
    with pytest.raises(PointsError) as exc:
        list(read_points(path))
    assert str(exc.value).startswith(f"{path}:{line}: ") and words in str(exc.value), str(exc.value)


POINT = {"frame_id": "a", "x_px": 1, "y_px": 2, "X_mm": 3, "Y_mm": 4, "Z_mm": 5}
K = {"fx_px": 3000, "fy_px": 3010, "cx_px": 2016, "cy_px": 1512}
JSON_BAD = [
    ([{"format": "dimenet-points/9"}], 1, "dimenet-points/9 is not a format this release reads"),
    ([{"format": 2}], 1, "format must be a string"),
    ([{"format": "dimenet-points/2"}, {**POINT, "fx_px": 1}], 2, "gives fx_px but not fy_px, cx_px, cy_px"),
    ([{"format": "dimenet-points/2"}, {**POINT, **K, "cx_px": "2016"}], 2, "cx_px must be a finite number"),
    ([{"format": "dimenet-points/2"}, {**POINT, **K}, POINT], 3, "(none) differ from the frame's first row"),
]


@pytest.mark.parametrize("objects, line, words", JSON_BAD)
def test_every_malformed_format_2_json_line_is_a_points_error_naming_the_line(tmp_path, objects, line, words):
    path = tmp_path / "rec.jsonl"
    path.write_text("\n".join(map(json.dumps, objects)) + "\n", encoding="utf-8")
    with pytest.raises(PointsError) as exc:
        list(read_points(path))
    assert str(exc.value).startswith(f"{path}:{line}: ") and words in str(exc.value), str(exc.value)
