"""Hostile and broken files: every reader answers with its typed error naming the file, fast and small.

Covers issue 20: truncated, bit-flipped and foreign .npz files, zip bombs and huge .npy headers
(refused before decoding), deeply nested JSON, out-of-range CSV numbers.
"""

import io
import json
import re
import struct
import time
import tracemalloc
import zipfile

import numpy as np
import pytest
from numpy.lib import format as npy

from dimenet.runtime.errors import DatasetError, LabelsError, PointsError, RigError
from dimenet.runtime.evaluation.calibration import read_calibration
from dimenet.runtime.formats import natural_labels
from dimenet.runtime.formats.dataset import Dataset, read_dataset, validate_arrays
from dimenet.runtime.formats.natural_labels import read_labels, read_object
from dimenet.runtime.formats.npz import MAX_NPZ_BYTES, read_npz
from dimenet.runtime.formats.points import read_points
from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import load_rig, paper_rig, rig_to_dict
from dimenet.runtime.formats.text import decimal

F, P = 3, 10


def dataset_arrays():
    rng = np.random.default_rng(0)
    valid = np.ones((F, P), bool)
    return {
        "format": np.array("dimenet-dataset/1"),
        "image_size": np.array([4032, 3024], np.int64),
        "points_2d": rng.uniform(0, 3000, (F, P, 2)),
        "points_3d": rng.normal(0, 100, (F, P, 3)),
        "valid": valid,
        "infer_mask": valid.copy(),
        "split": np.array(["train", "test", "test"]),
        "scene": np.array(["rig"] * F),
        "meta": np.array(json.dumps({"device": "unit-test"})),
    }


def calibration_arrays():
    K = np.array([[3000.0, 0, 2000], [0, 3000, 1500], [0, 0, 1]])
    return {
        "K_c": K,
        "K_star": np.stack([K] * F),
        "rvec": np.zeros((F, 3)),
        "tvec": np.ones((F, 3)),
        "e_star": np.ones(F),
    }


def truth_arrays():
    K = np.array([[3000.0, 0, 2000], [0, 3000, 1500], [0, 0, 1]])
    return {
        "frame_id": np.array([f"photo-{k:04d}.jpg" for k in range(F)]),
        "K": np.stack([K] * F),
        "rvec": np.zeros((F, 3)),
        "tvec": np.ones((F, 3)),
        "corners_px": np.zeros((F, P, 2)),
        "seen": np.ones((F, P), bool),
        "board_of_point": np.zeros(P, np.int64),
        "upside_down": np.zeros(F, bool),
        "covered_board": np.full(F, -1, np.int64),
        "image_size": np.array([4032, 3024], np.int64),
        "meta": np.array("{}"),
    }


# reader, its arrays, the array a crafted member replaces, written compressed (as the project writes it)?
READERS = {
    "dataset": (read_dataset, dataset_arrays, "points_2d", True),
    "calibration": (read_calibration, calibration_arrays, "K_star", False),
    "truth": (read_truth, truth_arrays, "corners_px", True),
}


def npz_bytes(arrays, compressed):
    out = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(out, **arrays)
    return out.getvalue()


def npy_header(shape, dtype="<f8"):
    out = io.BytesIO()
    npy.write_array_header_1_0(out, {"descr": dtype, "fortran_order": False, "shape": shape})
    return out.getvalue()


def write_with_member(path, arrays, key, payload, compress=zipfile.ZIP_DEFLATED):
    """An .npz of ``arrays`` whose member ``key`` is the raw ``payload`` (a crafted .npy)."""
    with zipfile.ZipFile(path, "w", compress) as z:
        for k, v in arrays.items():
            if k != key:
                b = io.BytesIO()
                npy.write_array(b, np.asanyarray(v), allow_pickle=False)
                z.writestr(k + ".npy", b.getvalue())
        z.writestr(key + ".npy", payload)
    return path


def refused(read, path, *words):
    """Call ``read(path)``: a typed error naming the file and every word; also quick and small."""
    tracemalloc.start()
    t = time.perf_counter()
    try:
        with pytest.raises(ValueError) as exc:
            read(path)
    finally:
        seconds = time.perf_counter() - t
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert isinstance(exc.value, (DatasetError, RigError, LabelsError, PointsError)), repr(exc.value)
    message = str(exc.value)
    assert str(path) in message, message
    for w in words:
        assert w in message, message
    return message, seconds, peak


@pytest.mark.parametrize("which", READERS)
def test_valid_files_still_read(tmp_path, which):
    read, arrays, _, compressed = READERS[which]
    path = tmp_path / f"{which}.npz"
    path.write_bytes(npz_bytes(arrays(), compressed))
    read(path)


@pytest.mark.parametrize("which", READERS)
def test_truncated_archive(tmp_path, which):
    read, arrays, _, compressed = READERS[which]
    good = npz_bytes(arrays(), compressed)
    for n, cut in enumerate((len(good) // 2, len(good) - 10)):
        path = tmp_path / f"cut{n}.npz"
        path.write_bytes(good[:cut])
        refused(read, path, "not a .npz (zip)")


@pytest.mark.parametrize("which", READERS)
def test_bit_flipped_member(tmp_path, which):
    read, arrays, key, compressed = READERS[which]
    good = npz_bytes(arrays(), compressed)
    info = zipfile.ZipFile(io.BytesIO(good)).getinfo(key + ".npy")
    data_start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    bad = bytearray(good)
    bad[data_start + info.compress_size - 20] ^= 0x10  # in the array data, past the .npy header
    path = tmp_path / "flipped.npz"
    path.write_bytes(bytes(bad))
    message, _, _ = refused(read, path, key, "corrupt")
    assert "CRC" in message or "decompress" in message


@pytest.mark.parametrize("which", READERS)
def test_npy_renamed_npz_and_random_bytes(tmp_path, which):
    read, arrays, key, _ = READERS[which]
    np.save(tmp_path / "array.npy", arrays()[key])
    (tmp_path / "array.npy").rename(tmp_path / "array.npz")
    refused(read, tmp_path / "array.npz", "a single .npy array, not a .npz")
    (tmp_path / "random.npz").write_bytes(np.random.default_rng(1).bytes(4000))
    message, _, _ = refused(read, tmp_path / "random.npz", "not a .npz (zip)")
    assert "pickle" not in message and "object" not in message  # it used to say "holds pickled object arrays"
    (tmp_path / "empty.npz").write_bytes(b"")
    refused(read, tmp_path / "empty.npz", "empty file")


@pytest.mark.parametrize("which", READERS)
def test_huge_header_is_refused_before_any_allocation(tmp_path, which):
    read, arrays, key, _ = READERS[which]
    payload = npy_header((10**8, 320, 2)) + bytes(1000)  # claims 512 GB
    path = write_with_member(tmp_path / "huge.npz", arrays(), key, payload)
    _, seconds, peak = refused(read, path, key, "(100000000, 320, 2)", f"at most {MAX_NPZ_BYTES} bytes")
    assert seconds < 1 and peak < 5_000_000


@pytest.mark.parametrize("which", READERS)
def test_zip_bomb_is_refused_before_decompression(tmp_path, which):
    """A member whose zip directory says it decompresses to 2 GiB (header and data consistent)."""
    read, arrays, key, _ = READERS[which]
    n = (1 << 31) // (320 * 2 * 8)
    header = npy_header((n, 320, 2))
    path = write_with_member(tmp_path / "bomb.npz", arrays(), key, header + bytes(1 << 16))
    claimed = len(header) + n * 320 * 2 * 8
    raw = bytearray(path.read_bytes())  # forge both uncompressed sizes: a real 2 GiB deflate stream takes seconds
    info = zipfile.ZipFile(path).getinfo(key + ".npy")
    raw[info.header_offset + 22 : info.header_offset + 26] = struct.pack("<I", claimed)
    central = [m.start() for m in re.finditer(b"PK\x01\x02", raw)]  # central directory entries
    entry = next(c for c in central if raw[c + 46 : c + 46 + len(info.filename)] == info.filename.encode())
    raw[entry + 24 : entry + 28] = struct.pack("<I", claimed)
    path.write_bytes(bytes(raw))
    assert zipfile.ZipFile(path).getinfo(key + ".npy").file_size == claimed
    _, seconds, peak = refused(read, path, key, f"decompresses to {claimed} bytes")
    assert seconds < 1 and peak < 5_000_000


def test_real_zip_bomb_under_a_small_cap(tmp_path):
    """A genuine deflated stream of zeros (4 MiB from ~4 KiB) against a 1 MiB cap: refused undecoded."""
    n = (4 << 20) // (320 * 2 * 8)
    payload = npy_header((n, 320, 2)) + bytes(n * 320 * 2 * 8)
    path = write_with_member(tmp_path / "bomb.npz", dataset_arrays(), "points_2d", payload)
    assert path.stat().st_size < 64_000

    def read(p):
        return read_npz(p, DatasetError, "dataset file", max_bytes=1 << 20)

    _, seconds, peak = refused(read, path, "points_2d", "at most 1048576 bytes")
    assert seconds < 1 and peak < 2_000_000


def test_member_larger_or_smaller_than_its_header_declares(tmp_path):
    for n, data in enumerate((bytes(1 << 20), bytes(100))):  # header declares 10·320·2 float64 = 51200 bytes
        path = write_with_member(tmp_path / f"m{n}.npz", dataset_arrays(), "points_2d", npy_header((10, 320, 2)) + data)
        refused(read_dataset, path, "points_2d", "corrupt or truncated")


def test_zero_size_dtype_cannot_declare_a_trillion_elements(tmp_path):
    path = write_with_member(tmp_path / "u0.npz", dataset_arrays(), "split", npy_header((10**12,), "<U0"))
    _, seconds, _ = refused(read_dataset, path, "split", "at most")
    assert seconds < 1


def test_object_members_and_foreign_members(tmp_path):
    arrays = dataset_arrays()
    arrays["meta"] = np.array([{"a": 1}], dtype=object)
    np.savez(tmp_path / "evil.npz", **arrays)
    refused(read_dataset, tmp_path / "evil.npz", "meta", "object arrays")
    with zipfile.ZipFile(tmp_path / "text.npz", "w") as z:
        z.writestr("notes.txt", "hello")
    refused(read_dataset, tmp_path / "text.npz", "'notes.txt' is not a .npy array")


def test_wrong_shapes_in_calibration_and_truth_are_refused(tmp_path):
    cal = calibration_arrays()
    cal["rvec"] = np.zeros((F + 1, 3))
    np.savez(tmp_path / "cal.npz", **cal)
    refused(read_calibration, tmp_path / "cal.npz", "rvec", "(F, 3)")
    truth = truth_arrays()
    truth["seen"] = np.ones((F, P + 1), bool)
    np.savez(tmp_path / "truth.npz", **truth)
    refused(read_truth, tmp_path / "truth.npz", "seen", "(N, P)")
    for meta, words in (('{"a": 1, "a": 2}', "'a' appears twice"), ("[1, 2]", "a JSON object")):
        truth = truth_arrays()
        truth["meta"] = np.array(meta)
        np.savez(tmp_path / "truth.npz", **truth)
        refused(read_truth, tmp_path / "truth.npz", "meta", words)


@pytest.mark.parametrize(
    "meta, words",
    [
        ("[" * 100_000 + "]" * 100_000, "nested deeper than 32"),
        ('{"a":' * 5000 + "1" + "}" * 5000, "nested deeper than 32"),
        ('{"a": ' + "9" * 5000 + "}", "the limit (4300"),  # CPython 3.9.2 says "(4300)", 3.11 "(4300 digits)"
        ('{"a": 1, "a": 2}', "'a' appears twice"),
    ],
)
def test_hostile_meta_json(tmp_path, meta, words):
    arrays = dataset_arrays()
    arrays["meta"] = np.array(meta)
    np.savez_compressed(tmp_path / "meta.npz", **arrays)
    refused(read_dataset, tmp_path / "meta.npz", "meta", words)


def test_image_size_beyond_int64_and_non_finite_point_named(tmp_path):
    arrays = dataset_arrays()
    arrays["image_size"] = np.array([2**64 - 1, 3024], np.uint64)  # used to wrap to -1 in int64
    np.savez(tmp_path / "size.npz", **arrays)
    refused(read_dataset, tmp_path / "size.npz", "image_size", "<= 1000000")
    arrays = dataset_arrays()
    arrays["points_3d"][2, 7, 1] = np.nan
    with pytest.raises(DatasetError, match=r"non-finite coordinate \(frame 2, point 7\)"):
        validate_arrays(arrays)


def test_empty_selection_says_so():
    ds = Dataset(**validate_arrays(dataset_arrays()))
    with pytest.raises(DatasetError, match="none of the dataset's 3 frames is selected"):
        ds.select(ds.frames_in("val"))


def rig_text(change=None):
    d = rig_to_dict(paper_rig())
    if change:
        change(d)
    return json.dumps(d)


def board0(key, value):
    return lambda d: d["boards"][0].__setitem__(key, value)


@pytest.mark.parametrize(
    "text, words",
    [
        ("[" * 100_000 + "]" * 100_000, "nested deeper than 32"),
        ('{"a":' * 100_000 + "1" + "}" * 100_000, "nested deeper than 32"),
        (rig_text().replace('"square_mm": 22.0', '"square_mm": ' + "9" * 5000, 1), "the limit (4300"),
        (rig_text()[:-1] + ', "units": "mm"}', "'units' appears twice"),
        (rig_text(board0("square_mm", 1e300)), "boards[0].square_mm: must be at most 1e+06"),
        (rig_text(lambda d: d["boards"][1]["tvec_mm"].__setitem__(2, -1e300)), "boards[1].tvec_mm[2]"),
        (rig_text(board0("rvec", [0.0, 0.0, 7.0])), "boards[0].rvec: must be an axis-angle of at most 2 pi"),
        (rig_text(board0("inner_corners", [10**9, 10**9])), "boards[0].inner_corners: must be 2 integers in [2, 1000]"),
        (rig_text(board0("square_mm", 10**400)), "boards[0].square_mm: must be at most"),
        (
            rig_text(board0("aruco", {"dictionary": "DICT_4X4_50", "first_id": 10**30, "marker_mm": 16.0})),
            "boards[0].aruco.first_id: the board's 49 markers",
        ),
        (rig_text()[:-1] + ', "x": "' + "y" * (1 << 20) + '"}', "larger than 1048576 bytes"),
    ],
)
def test_hostile_rig_json(tmp_path, text, words):
    path = tmp_path / "rig.json"
    path.write_text(text, encoding="utf-8")
    refused(load_rig, path, words)


def test_rig_bytes_and_bom(tmp_path):
    path = tmp_path / "rig.json"
    path.write_bytes(b'{"format": "dimenet-rig/1",\n"units": "mm\xe9"}')
    refused(load_rig, path, f"{path}:2:", "not UTF-8")
    path.write_bytes(b"\xef\xbb\xbf" + rig_text().encode())  # Windows Notepad's UTF-8: accepted
    assert load_rig(path) == paper_rig()


OBJECT = "point_id,X_mm,Y_mm,Z_mm\nroof-1,-300.0,-80.0,-50.0\nroof-2,-290.0,-80.0,-50.0\n"


@pytest.mark.parametrize(
    "row, words",
    [
        ("roof-3,1e300,0,0", ":4: X_mm must be at most 1e+06 in magnitude, got '1e300'"),
        ("roof-3,0,1e400,0", ":4: Y_mm must be a finite number"),
        ("roof-3,0,0,1_000", ":4: Z_mm must be a finite number, got '1_000'"),
        ("roof-3,\u0661\u0662,0,0", ":4: X_mm must be a finite number"),
        ("roof-3," + "1" * 200_000 + ",0,0", ":4: not a readable CSV row (field larger than field limit"),
        ('"roof\n3",0,0,0\nroof-4,x,0,0', ":6: X_mm must be a finite number"),  # a row named by its first line
    ],
)
def test_hostile_object_csv(tmp_path, row, words):
    path = tmp_path / "OBJECT.csv"
    path.write_text(OBJECT + row + "\n", encoding="utf-8")
    refused(read_object, path, words)


def test_hostile_csv_bytes_sizes_and_labels(tmp_path, monkeypatch):
    path = tmp_path / "OBJECT.csv"
    path.write_bytes(OBJECT.encode() + b"roof-3,0,\xff,0\n")
    refused(read_object, path, f"{path}:4: not UTF-8")
    path.write_bytes(b"\xef\xbb\xbf" + OBJECT.encode())
    obj = read_object(path)
    monkeypatch.setattr(natural_labels, "MAX_OBJECT_POINTS", 1)
    refused(read_object, path, f"{path}:3: more than 1 rows")
    monkeypatch.setattr(natural_labels, "MAX_CSV_BYTES", 100)
    path.write_text(OBJECT + "".join(f"p{k},0,0,0\n" for k in range(10)))
    refused(read_object, path, "larger than 100 bytes")
    labels = tmp_path / "LABELS.csv"
    labels.write_text("image,point_id,x_px,y_px\nIMG_1.jpg,roof-1,1e300,904.0\n")
    refused(lambda p: read_labels(p, obj), labels, ":2: x_px must be at most 1e+06")


# Points files (issue 33): what the points CSV reads as a number is what the labels reader reads.
POINTS_HEADER = "frame_id,t_ns,x_px,y_px,X_mm,Y_mm,Z_mm\n"


def read_all_points(path):
    return list(read_points(path))


@pytest.mark.parametrize(
    "row, words",
    [
        (f"a,{'9' * 5000},1,2,3,4,5", ":2: t_ns must be an integer of nanoseconds"),  # int()'s 4300-digit limit
        (f"a,{'1' * 20},1,2,3,4,5", ":2: t_ns must be an integer of nanoseconds"),
        ("a,\u0661\u0662,1,2,3,4,5", ":2: t_ns must be an integer"),
        ("a,1,1_000,2,3,4,5", ":2: x_px must be a number, got '1_000'"),
        ("a,1,1,\u0661\u0662,3,4,5", ":2: y_px must be a number, got '١٢'"),
        ("a,1,1,2,\uff11\uff12,4,5", ":2: X_mm must be a number, got '１２'"),
        ("a,1,1,2,3,\u00a012,5", ":2: Y_mm must be a number"),  # a Unicode space float() would strip
        ("a,1,1,2,3,4,nan", ":2: coordinates must be finite numbers"),
    ],
)
def test_hostile_points_csv(tmp_path, row, words):
    path = tmp_path / "rec.csv"
    path.write_text(POINTS_HEADER + row + "\n", encoding="utf-8")
    refused(read_all_points, path, words)


def test_points_csv_numbers_that_stay_readable(tmp_path):
    path = tmp_path / "rec.csv"
    path.write_text(POINTS_HEADER + f"a,{'0' * 24}7, 12.5 ,+2,.5,4.,1e2\n", encoding="utf-8")
    (frame,) = read_points(path)
    assert (
        frame.t_ns == 7
        and frame.points_2d.tolist() == [[12.5, 2.0]]
        and frame.points_3d.tolist() == [[0.5, 4.0, 100.0]]
    )
    assert decimal(" 12.5 ") == 12.5 and decimal("1_000") is None and decimal("\u0661") is None and decimal("x") is None


def test_points_jsonl_t_ns_of_5000_digits(tmp_path):
    path = tmp_path / "rec.jsonl"
    point = '"x_px": 1, "y_px": 2, "X_mm": 3, "Y_mm": 4, "Z_mm": 5'
    path.write_text('{"frame_id": "a", "t_ns": ' + "9" * 5000 + ", " + point + "}\n", encoding="utf-8")
    refused(read_all_points, path, ":1: not valid JSON")
