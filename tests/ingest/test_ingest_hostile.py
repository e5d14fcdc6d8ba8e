"""Hostile input to `dimenet ingest`: one bad photo or CSV row never aborts the run nor costs the pixels it claims.

One good photo is rendered at 1/3 of 4032x3024 px (as tests/ingest/test_ingest.py does); the bad
photos beside it are crafted: a 5000x1 and a 1x5000 image, a truncated JPEG, the good JPEG with
its frame header claiming 30000x30000 px, a 333-byte JPEG claiming the same, a PNG claiming
100000x100000 px (more than OpenCV itself decodes), an empty file, random bytes named .jpg, a
16x16 px image and a 5:1 strip.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from dimenet.runtime.cli.commands import ingest as ingest_command
from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import LabelsError, PhotoError
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.natural_labels import ImageLabels, NaturalObject
from dimenet.runtime.formats.rig import paper_rig
from dimenet.runtime.ingest import pipeline
from dimenet.runtime.ingest.detection import detect_boards
from dimenet.runtime.ingest.photo import MAX_MEGAPIXELS, header_size, read_photo
from dimenet.runtime.ingest.pipeline import ingest, report
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import scaled_profile, write_render

SCALE = 3.0  # 1344 x 1008 px


def jpeg_claiming(jpeg: bytes, width: int, height: int) -> bytes:
    """The JPEG with its frame header (SOFn) patched to claim ``width`` x ``height`` px."""
    data, pos = bytearray(jpeg), 2
    while data[pos + 1] not in range(0xC0, 0xC4):
        pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    data[pos + 5 : pos + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    return bytes(data)


def png_claiming(width: int, height: int) -> bytes:
    """A 16x16 PNG whose IHDR claims ``width`` x ``height`` px (CRC fixed, so only the size is wrong)."""
    import zlib

    data = bytearray(cv2.imencode(".png", np.full((16, 16), 128, np.uint8))[1].tobytes())
    data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    data[29:33] = zlib.crc32(bytes(data[12:29])).to_bytes(4, "big")
    return bytes(data)


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    folder = tmp_path_factory.mktemp("good")
    write_render(folder, paper_rig(), scaled_profile(get_profile("galaxy-s8"), SCALE), 1, seed=0)
    return folder / "photo-0000.jpg"


@pytest.fixture(scope="module")
def ingested(good):
    return ingest([good], paper_rig())


# name -> words its report's reason holds
HOSTILE = {
    "strip-5000x1.png": "5000x1 px is too small (every side needs >= 64 px)",
    "strip-1x5000.png": "1x5000 px is too small",
    "truncated.jpg": "truncated.jpg: cannot decode the image",
    "claims-30000.jpg": "claims-30000.jpg: 30000x30000 px is 900.0 MP, over the 50 MP cap",
    "header-30000.jpg": "header-30000.jpg: 30000x30000 px is 900.0 MP, over the 50 MP cap",
    "claims-100000.png": "100000x100000 px is 10000.0 MP, over the 50 MP cap",
    "empty.jpg": "empty.jpg: empty file",
    "random.jpg": "random.jpg: unsupported image format",
    "tiny.jpg": "16x16 px is too small",
    "pano.png": "1000x200 px has an aspect ratio of 5.0:1, over 4:1",
}


@pytest.fixture(scope="module")
def hostile(good, tmp_path_factory):
    folder = tmp_path_factory.mktemp("hostile")
    jpeg = good.read_bytes()
    tiny = cv2.imencode(".jpg", np.full((16, 16), 128, np.uint8))[1].tobytes()
    files = {
        "strip-5000x1.png": cv2.imencode(".png", np.full((1, 5000), 128, np.uint8))[1].tobytes(),
        "strip-1x5000.png": cv2.imencode(".png", np.full((5000, 1), 128, np.uint8))[1].tobytes(),
        "truncated.jpg": jpeg[: len(jpeg) // 2],
        "claims-30000.jpg": jpeg_claiming(jpeg, 30000, 30000),
        "header-30000.jpg": jpeg_claiming(tiny, 30000, 30000),
        "claims-100000.png": png_claiming(100000, 100000),
        "empty.jpg": b"",
        "random.jpg": np.random.default_rng(0).bytes(5000),
        "tiny.jpg": tiny,
        "pano.png": cv2.imencode(".png", np.full((200, 1000), 128, np.uint8))[1].tobytes(),
    }
    assert set(files) == set(HOSTILE)
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return [folder / name for name in HOSTILE]


def test_every_bad_photo_is_skipped_with_its_reason_and_the_run_completes(good, hostile, tmp_path, capsys):
    out = tmp_path / "shots.npz"
    assert main(["ingest", str(good), *map(str, hostile), "--rig", "paper", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert list(read_dataset(out).frame_id) == [good.name]
    rep = json.loads((tmp_path / "shots.report.json").read_text())
    photos = {p["photo"]: p for p in rep["photos"]}
    assert list(photos) == [good.name, *HOSTILE]
    assert photos[good.name]["skipped"] is None and len(photos[good.name]["boards"]) >= 2
    for name, words in HOSTILE.items():
        assert words in photos[name]["skipped"], name
        assert f"{name}  skipped: " in printed
    assert rep["totals"]["frames"] == 1 and rep["totals"]["skipped"] == len(HOSTILE)


def test_a_claimed_30000x30000_jpeg_is_refused_from_its_header_without_decoding(hostile, monkeypatch):
    claims = next(p for p in hostile if p.name == "claims-30000.jpg")
    assert claims.stat().st_size < 400_000 and header_size(claims.read_bytes()) == (30000, 30000)

    def no_decoding(*args, **kwargs):
        raise AssertionError("decoded a photo refused by its header")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    with pytest.raises(PhotoError, match="claims-30000.jpg: 30000x30000 px is 900.0 MP"):
        read_photo(claims)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads VmHWM from /proc (Linux)")
def test_peak_memory_of_reading_a_claimed_30000x30000_jpeg_stays_small(hostile):
    claims = next(p for p in hostile if p.name == "claims-30000.jpg")
    code = (  # VmHWM: this process image's peak RSS (ru_maxrss would carry over the forking pytest's)
        "import sys\n"
        "from dimenet.runtime.ingest.photo import read_photo\n"
        "try:\n    read_photo(sys.argv[1])\nexcept ValueError:\n    pass\n"
        "print(next(l for l in open('/proc/self/status') if l.startswith('VmHWM')).split()[1])\n"
    )
    done = subprocess.run([sys.executable, "-c", code, str(claims)], capture_output=True, text=True, timeout=120)
    peak_mb = int(done.stdout.split()[-1]) / 1024  # kB
    assert peak_mb < 300, f"peak RSS {peak_mb:.0f} MB (decoding would take ~1.8 GB)"


def test_max_megapixels_moves_the_cap(good, tmp_path, capsys):
    assert MAX_MEGAPIXELS == 50
    out = tmp_path / "one.npz"
    assert main(["ingest", str(good), "--rig", "paper", "--out", str(out), "--max-megapixels", "1"]) == 2
    rep = json.loads((tmp_path / "one.report.json").read_text())
    assert (
        "1344x1008 px is 1.4 MP, over the 1 MP cap (dimenet ingest --max-megapixels raises it)"
        in (rep["photos"][0]["skipped"])
    )
    assert not out.exists()
    assert main(["ingest", str(good), "--rig", "paper", "--out", str(out), "--max-megapixels", "1.5"]) == 0
    assert list(read_dataset(out).frame_id) == [good.name]
    capsys.readouterr()
    for bad in ("0", "-3", "nan", "inf", "2000", "lots"):
        assert main(["ingest", str(good), "--rig", "paper", "--out", str(out), "--max-megapixels", bad]) == 2
        err = capsys.readouterr().err
        assert "--max-megapixels" in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize(
    "ext, params",
    [
        (".jpg", []),
        (".png", []),
        (".bmp", []),
        (".tiff", []),
        (".webp", []),
        (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]),
    ],
)
def test_the_header_gives_the_size_the_decoder_gives(ext, params, tmp_path):
    image = np.random.default_rng(0).integers(0, 255, (72, 96, 3), dtype=np.uint8)
    data = cv2.imencode(ext, image, params)[1].tobytes()
    assert header_size(data) == (96, 72)
    path = tmp_path / f"photo{ext}"
    path.write_bytes(data)
    assert read_photo(path).gray.shape == (72, 96)


def test_pnm_headers_and_formats_without_a_size_check(tmp_path):
    assert header_size(b"P5\n# a comment\n96 72\n255\n" + bytes(96 * 72)) == (96, 72)
    assert header_size(cv2.imencode(".ppm", np.zeros((72, 96, 3), np.uint8))[1].tobytes()) == (96, 72)
    raster = tmp_path / "photo.sr"  # Sun raster: OpenCV reads it, its size is not checked first, so it is refused
    raster.write_bytes(cv2.imencode(".sr", np.zeros((72, 96), np.uint8))[1].tobytes())
    with pytest.raises(PhotoError, match="photo.sr: unsupported image format for ingest"):
        read_photo(raster)
    with pytest.raises(PhotoError, match="cut.png: cannot decode the image .corrupt or truncated header"):
        (tmp_path / "cut.png").write_bytes(png_claiming(100, 100)[:20])
        read_photo(tmp_path / "cut.png")


@pytest.mark.parametrize(
    "error, words",
    [
        (np.linalg.LinAlgError("SVD did not converge"), "numeric failure while identifying the boards (LinAlgError"),
        (FloatingPointError("overflow encountered"), "numeric failure while identifying the boards (FloatingPoint"),
        (OverflowError("math range error"), "numeric failure while identifying the boards (OverflowError"),
    ],
)
def test_a_numeric_failure_in_one_photo_skips_that_photo(good, monkeypatch, error, words):
    def label(*args, **kwargs):
        raise error

    monkeypatch.setattr(pipeline, "label", label)
    result = ingest([good], paper_rig())
    assert result.dataset is None and words in result.results[0].skipped


def test_an_opencv_error_in_detection_skips_that_photo_and_others_go_on(good, tmp_path, monkeypatch):
    copy = tmp_path / "copy.jpg"
    copy.write_bytes(good.read_bytes())
    real = pipeline.detect_boards

    def detect(gray, rig, place=None):  # the first photo goes through as if it were 5000x1 px
        gray = np.zeros((1, 5000), np.uint8) if detect.calls == 0 else gray
        detect.calls += 1
        return real(gray, rig, place)

    detect.calls = 0
    monkeypatch.setattr(pipeline, "detect_boards", detect)
    result = ingest([good, copy], paper_rig())
    assert "OpenCV failed while finding the boards (resize" in result.results[0].skipped
    assert result.results[1].skipped is None and list(result.dataset.frame_id) == ["copy.jpg"]
    with pytest.raises(cv2.error):
        detect_boards(np.zeros((1, 5000), np.uint8), paper_rig())  # what the photo would have raised


@pytest.mark.parametrize("error", [KeyboardInterrupt, MemoryError])
def test_interrupts_and_memory_errors_are_not_swallowed(good, monkeypatch, error):
    def detect(*args, **kwargs):
        raise error()

    monkeypatch.setattr(pipeline, "detect_boards", detect)
    with pytest.raises(error):
        ingest([good], paper_rig())


def test_the_dataset_is_written_before_the_report(good, ingested, tmp_path, monkeypatch):
    monkeypatch.setattr(ingest_command, "ingest", lambda *args, **kwargs: ingested)
    written = []
    real_dataset, real_text = ingest_command.write_dataset, ingest_command.atomic_write_text

    def write_dataset(dataset, path):
        written.append("dataset")
        return real_dataset(dataset, path)

    def write_text(path, text):
        written.append("report")
        return real_text(path, text)

    monkeypatch.setattr(ingest_command, "write_dataset", write_dataset)
    monkeypatch.setattr(ingest_command, "atomic_write_text", write_text)
    assert main(["ingest", str(good), "--rig", "paper", "--out", str(tmp_path / "a.npz")]) == 0
    assert written == ["dataset", "report"]


def test_a_failed_dataset_write_leaves_no_report(good, ingested, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(ingest_command, "ingest", lambda *args, **kwargs: ingested)

    def full_disk(dataset, path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ingest_command, "write_dataset", full_disk)
    assert main(["ingest", str(good), "--rig", "paper", "--out", str(tmp_path / "a.npz")]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and err.count("\n") == 1
    assert not (tmp_path / "a.report.json").exists() and not (tmp_path / "a.npz").exists()


def test_an_absurd_object_point_is_a_one_line_error_before_any_photo(good, tmp_path, monkeypatch, capsys):
    obj = tmp_path / "object.csv"
    obj.write_text("point_id,X_mm,Y_mm,Z_mm\np0,1,2,3\np1,1e300,0,-50\np2,4,5,6\n")
    labels = tmp_path / "labels.csv"
    labels.write_text(f"image,point_id,x_px,y_px\n{good.name},p0,10,20\n")

    def no_photo(*args, **kwargs):
        raise AssertionError("a photo was processed")

    monkeypatch.setattr(pipeline, "ingest_photo", no_photo)
    out = tmp_path / "n.npz"
    argv = ["ingest", str(good), "--rig", "paper", "--out", str(out), "--object", str(obj), "--labels", str(labels)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "object.csv" in err and "1e+300" in err.replace("1e300", "1e+300")
    assert not out.exists() and not (tmp_path / "n.report.json").exists()
    huge = NaturalObject(point_ids=("p0", "p1"), points_mm=np.array([[0.0, 0, 0], [0, 0, 1e300]]))
    with pytest.raises(LabelsError, match="OBJECT.csv: point 'p1': Z_mm = 1e\\+300 lies beyond"):
        ingest([good], paper_rig(), obj=huge, labels={})


def test_labels_far_outside_one_photo_skip_that_photo_only(good, tmp_path):
    copy = tmp_path / "unlabelled.jpg"
    copy.write_bytes(good.read_bytes())
    obj = NaturalObject(point_ids=("a", "b"), points_mm=np.array([[0.0, 0, -50], [10, 0, -50]]))
    far = ImageLabels(index=np.array([0, 1]), points_px=np.array([[100.0, 100], [5000.0, 10]]))
    result = ingest([good, copy], paper_rig(), obj=obj, labels={good.name: far})
    assert result.results[0].skipped == (
        "labels: point 'b' at (5000, 10) px lies far outside the 1344x1008 px image "
        "(a label may lie at most 1 image size(s) beyond its edges)"
    )
    assert list(result.dataset.frame_id) == ["unlabelled.jpg"]
    assert report(result, paper_rig())["photos"][0]["labels"] == 2
