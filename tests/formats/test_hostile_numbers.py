"""Every number of every text format, replaced in turn by each of the fuzz's hostile numbers (past float64, past
int()'s 4300 digits, past the 64-bit clock, non-ASCII digits, ``1_000``, ``0x10``, ...): the reader ends in its typed
error or reads a file, never another exception. The exhaustive twin of the fuzz's random "a hostile number"
mutation (``bench.fuzz.HOSTILE_NUMBERS``); it found the points format's declared version and the motion reader's
t_ns read by ``str.isdigit()`` and ``int()``."""

import json
import re

import numpy as np
import pytest

from dimenet.runtime.bench.fuzz import HOSTILE_NUMBERS
from dimenet.runtime.errors import DimenetError
from dimenet.runtime.formats.camera_file import FORMATS, read_camera, write_camera
from dimenet.runtime.formats.motion import read_motion, write_gyro, write_lens_shift
from dimenet.runtime.formats.natural_labels import read_labels, read_object
from dimenet.runtime.formats.points import read_points, write_points
from dimenet.runtime.formats.rig import load_rig, paper_rig, rig_to_dict
from dimenet.runtime.rectify.user_camera import checked_camera

NUMBER = re.compile(r"[-+]?[0-9][0-9.eE+-]*")
OBJECT = "point_id,X_mm,Y_mm,Z_mm\nroof-1,-300.0,-80.0,-50.0\nroof-2,-290.5,-80.0,-50.0\n"


def _points_rows():
    return [
        (f"f{i}", 1000 * i, 10.0 * j, 5.0 * j, float(j), float(j * j), 500.0, 3000.0, 3000.0, 2000.0, 1500.0)
        for i in range(2)
        for j in range(3)
    ]


def _points_jsonl(path):
    keys = ("frame_id", "t_ns", "x_px", "y_px", "X_mm", "Y_mm", "Z_mm", "fx_px", "fy_px", "cx_px", "cy_px")
    lines = [json.dumps({"format": "dimenet-points/2"})] + [json.dumps(dict(zip(keys, r))) for r in _points_rows()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _all_points(path):
    return list(read_points(path))  # the reader is lazy: read to the end


def _sources():
    """(name, file name, writer of a clean file into a folder, its reader)."""
    camera = checked_camera(
        np.array([[3000.0, 0, 2015.5], [0, 3001.0, 1511.5], [0, 0, 1]]),
        (4032, 3024),
        "c",
        np.array([0.1, -0.05, 0.001, 0.002]),
    )
    times = np.arange(1, 4) * 1_000_000
    yield "points csv", "p.csv", lambda d: write_points(d / "p.csv", _points_rows(), frame_k_c=True), _all_points
    yield "points jsonl", "p.jsonl", lambda d: _points_jsonl(d / "p.jsonl"), _all_points
    yield "gyroscope", "g.csv", lambda d: write_gyro(d / "g.csv", np.c_[times, np.full((3, 3), 0.01)]), read_motion
    yield (
        "lens shift",
        "o.csv",
        lambda d: write_lens_shift(d / "o.csv", np.c_[times, np.full((3, 2), 1.5)]),
        read_motion,
    )
    for fmt in FORMATS:
        yield f"camera {fmt}", f"c.{fmt}", lambda d, fmt=fmt: write_camera(d / f"c.{fmt}", camera, fmt), read_camera

    def rig(d):
        (d / "rig.json").write_text(json.dumps(rig_to_dict(paper_rig())), encoding="utf-8")
        return d / "rig.json"

    yield "rig", "rig.json", rig, load_rig

    def obj(d):
        (d / "OBJECT.csv").write_text(OBJECT, encoding="utf-8")
        return d / "OBJECT.csv"

    yield "object", "OBJECT.csv", obj, read_object

    def labels(d):
        (d / "LABELS.csv").write_text("image,point_id,x_px,y_px\na.jpg,roof-1,10.5,20\na.jpg,roof-2,30,40\n")
        return d / "LABELS.csv"

    yield "labels", "LABELS.csv", labels, lambda p: read_labels(p, read_object(obj(p.parent)))


@pytest.mark.parametrize("file_name, write, read", [pytest.param(*s[1:], id=s[0]) for s in _sources()])
def test_every_number_replaced_by_a_hostile_one_is_read_or_refused_typed(tmp_path, file_name, write, read):
    clean = write(tmp_path).read_text(encoding="utf-8")
    read(tmp_path / file_name)  # the clean file reads
    numbers = list(NUMBER.finditer(clean))
    assert numbers
    path = tmp_path / f"mutated-{file_name}"
    for m in numbers[:80]:
        for hostile in HOSTILE_NUMBERS:
            path.write_text(clean[: m.start()] + hostile + clean[m.end() :], encoding="utf-8")
            try:
                read(path)
            except DimenetError:
                pass
