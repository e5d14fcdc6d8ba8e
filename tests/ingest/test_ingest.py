"""Photos -> dataset: rendered photos of the rig go through `ingest` and are scored against the renderer's truth.

The photos are rendered at 1/3 of the Galaxy S8's 4032x3024 px (same field of view) to keep the
suite fast; the 12 MP figures come from ``dimenet bench --ingest``.
"""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from dimenet.runtime.bench.ingest_score import score
from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import IdentificationError, IngestError, LabelsError, PhotoError
from dimenet.runtime.evaluation.calibration import calibrate_dataset, read_calibration
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.natural_labels import read_labels, read_object
from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import Aruco, Board, Rig, paper_rig
from dimenet.runtime.geometry import k_params, matrix_to_rvec, project, rvec_to_matrix
from dimenet.runtime.ingest.detection import Detection, detect_boards
from dimenet.runtime.ingest.identity import identify, rough_k
from dimenet.runtime.ingest.outcome import NOT_FOUND
from dimenet.runtime.ingest.photo import exif_orientation, read_photo
from dimenet.runtime.ingest.pipeline import auto_split, ingest, report
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, scaled_profile, write_render

SCALE = 3.0  # 1344 x 1008 px photos
N_PHOTOS = 10  # photos 1 and 6 upside down, 3 and 8 with a board covered


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    folder = tmp_path_factory.mktemp("shots")
    write_render(folder, paper_rig(), scaled_profile(get_profile("galaxy-s8"), SCALE), N_PHOTOS, seed=0)
    return folder, read_truth(folder / TRUTH_FILE)


@pytest.fixture(scope="module")
def ingested(rendered):
    folder, truth = rendered
    return ingest([folder / str(f) for f in truth.frame_id], paper_rig())


def board_rms(points_px: np.ndarray, truth_px: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((points_px - truth_px) ** 2, axis=1))))


def test_render_truth_is_the_projection_through_the_simulators_camera(rendered):
    folder, truth = rendered
    rig = paper_rig()
    assert cv2.imread(str(folder / truth.frame_id[0])).shape == (1008, 1344, 3)
    for k in range(N_PHOTOS):
        np.testing.assert_allclose(truth.corners_px[k], project(rig.points(), truth.K[k], truth.rvec[k], truth.tvec[k]))
        image_y_in_rig = rvec_to_matrix(truth.rvec[k])[1]  # the image's y axis (down) in {W}, whose y points down
        assert (image_y_in_rig[1] < 0) == truth.upside_down[k]
        shown = truth.seen[k].reshape(4, 80).all(1)
        assert shown.sum() >= 2 and np.array_equal(truth.seen[k].reshape(4, 80).any(1), shown)
    assert np.flatnonzero(truth.upside_down).tolist() == [1, 6]
    assert np.flatnonzero(truth.covered_board >= 0).tolist() == [3, 8]
    fx = k_params(truth.K)[:, 0]
    assert np.all(np.abs(fx - get_profile("galaxy-s8").focal_px / SCALE) < 0.02 * fx)  # focus breathing only


def test_ingest_finds_identifies_and_refines_the_boards(rendered, ingested):
    folder, truth = rendered
    s = score(ingested.dataset, truth)
    assert s.detection_rate >= 0.95
    assert s.identity_errors == 0
    assert s.corner_rms_px <= 0.1
    accepted = [r.name for r in ingested.results if r.skipped is None]
    assert list(ingested.dataset.frame_id) == accepted and len(accepted) >= N_PHOTOS - 1


@pytest.mark.parametrize("photo", [1, 6, 3, 8])
def test_upside_down_and_covered_photos_keep_their_identities(rendered, ingested, photo):
    folder, truth = rendered
    ds = ingested.dataset
    frame = list(ds.frame_id).index(truth.frame_id[photo])
    valid = ds.valid[frame, :320].reshape(4, 80)
    found = valid.all(1)
    assert np.all(found >= truth.seen[photo].reshape(4, 80).all(1))  # every board shown whole is found
    for b in np.flatnonzero(found):
        sl = slice(80 * b, 80 * b + 80)
        assert board_rms(ds.points_2d[frame, sl], truth.corners_px[photo, sl]) < 0.3  # right board, right way round
    if truth.covered_board[photo] >= 0:
        assert not valid[truth.covered_board[photo]].any()


@pytest.mark.parametrize("photo", [3, 8])
def test_the_report_says_a_covered_board_is_hidden_where_the_camera_puts_it(rendered, ingested, photo):
    _, truth = rendered
    result = next(r for r in ingested.results if r.name == truth.frame_id[photo])
    line = next(line for line in result.board_lines if line.board == truth.covered_board[photo])
    assert line.status == NOT_FOUND and line.why.startswith("in view of the photo's camera, hidden: ")
    assert 0 < int(line.why.split("hidden: ")[1].split(" of ")[0]) <= 80


@pytest.mark.parametrize("workers", [2, 3])  # two threads; and a helper process
def test_workers_give_the_same_results_in_the_photos_order(rendered, workers):
    folder, truth = rendered
    photos = [folder / str(f) for f in truth.frame_id[:4]][::-1]  # not in file order
    one, more = ingest(photos, paper_rig(), workers=1), ingest(photos, paper_rig(), workers=workers)
    assert [r.name for r in more.results] == [p.name for p in photos]
    assert report(one, paper_rig()) == report(more, paper_rig())
    np.testing.assert_array_equal(one.dataset.points_2d, more.dataset.points_2d)


def test_k_star_of_the_ingested_dataset_is_the_renderers_k(rendered, ingested):
    folder, truth = rendered
    ds = ingested.dataset
    cal = calibrate_dataset(ds)
    rows = [list(truth.frame_id).index(f) for f in ds.frame_id]
    assert np.abs(k_params(cal.K_star) - k_params(truth.K[rows])).mean() <= 1.0


def test_report_names_every_photo_and_why_one_was_skipped(rendered, tmp_path):
    folder, truth = rendered
    good = folder / str(truth.frame_id[0])
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((1008, 1344), 128, np.uint8))
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(good.read_bytes()[:3000])
    small = tmp_path / "small.jpg"
    cv2.imwrite(str(small), cv2.resize(cv2.imread(str(good)), (672, 504)))
    result = ingest([good, blank, broken, small], paper_rig(), split="train")
    rep = report(result, paper_rig())
    photos = {p["photo"]: p for p in rep["photos"]}
    assert list(photos) == [good.name, "blank.png", "broken.jpg", "small.jpg"]
    first = photos[good.name]
    assert first["skipped"] is None and first["split"] == "train" and first["corners"] == 80 * len(first["boards"])
    assert first["rms_px"] < 0.2 and first["runner_up_rms_px"] > 3 * first["rms_px"]
    np.testing.assert_allclose(first["K_px"], k_params(truth.K[0]), atol=2.0)
    assert photos["blank.png"]["skipped"] == "0 board(s) found, a rig photo needs 2"
    assert "broken.jpg: cannot decode" in photos["broken.jpg"]["skipped"]
    assert "image size 672x504 px differs" in photos["small.jpg"]["skipped"]
    assert (
        rep["totals"]["frames"] == 1 and rep["totals"]["skipped"] == 3 and rep["totals"]["image_size"] == [1344, 1008]
    )


def test_cli_photos_to_ingest_to_calibrate(rendered, tmp_path, capsys):
    folder, truth = rendered
    photos = [str(folder / str(f)) for f in truth.frame_id[:4]]
    data = tmp_path / "shots.npz"
    assert main(["ingest", *photos, "--rig", "paper", "--out", str(data), "--split", "train"]) == 0
    out = capsys.readouterr().out
    assert "4 frames (4 train, 0 test) from 4 photos, 0 skipped" in out and "photo-0001.jpg  train  " in out
    rep = json.loads((tmp_path / "shots.report.json").read_text())
    assert [p["photo"] for p in rep["photos"]] == [f"photo-{k:04d}.jpg" for k in range(4)]
    ds = read_dataset(data)
    assert list(ds.frame_id) == [f"photo-{k:04d}.jpg" for k in range(4)] and set(ds.scene) == {"rig"}
    assert main(["calibrate", str(data), "--out", str(tmp_path / "cal.npz")]) == 0
    K_star = read_calibration(tmp_path / "cal.npz").K_star
    assert np.abs(k_params(K_star) - k_params(truth.K[:4])).mean() <= 1.0


def test_cli_render_writes_photos_and_truth(tmp_path, capsys):
    assert (
        main(
            [
                "render",
                "--rig",
                "paper",
                "--profile",
                "galaxy-s8",
                "--n",
                "2",
                "--scale",
                "8",
                "--format",
                "png",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    assert "2 photos of 504x378 px" in capsys.readouterr().out
    truth = read_truth(tmp_path / TRUTH_FILE)
    assert list(truth.frame_id) == ["photo-0000.png", "photo-0001.png"]
    assert cv2.imread(str(tmp_path / "photo-0001.png")).shape == (378, 504, 3)


def test_split_auto_is_a_stable_80_20_hash_of_the_file_name(ingested):
    names = [f"IMG_{k:05d}.JPG" for k in range(4000)]
    train = np.mean([auto_split(n) == "train" for n in names])
    assert 0.77 < train < 0.83
    assert [auto_split(n) for n in names[:50]] == [auto_split(n) for n in names[:50]]
    ds = ingested.dataset
    assert list(ds.split) == [auto_split(str(n)) for n in ds.frame_id]  # the name alone decides
    assert ds.meta["split"] == "auto"


def _natural_files(tmp_path, truth, photo, rng):
    """OBJECT.csv: 12 points off the boards in {W}; LABELS.csv: their true pixels in ``photo`` + 1 px noise."""
    points = np.c_[rng.uniform(-200, 200, (12, 2)), rng.uniform(-150, -20, 12)]
    obj = tmp_path / "object.csv"
    obj.write_text("point_id,X_mm,Y_mm,Z_mm\n" + "".join(f"p{k},{x},{y},{z}\n" for k, (x, y, z) in enumerate(points)))
    px = project(points, truth.K[photo], truth.rvec[photo], truth.tvec[photo]) + rng.normal(0, 1.0, (12, 2))
    labels = tmp_path / "labels.csv"
    labels.write_text(
        "image,point_id,x_px,y_px\n"
        + "".join(f"{truth.frame_id[photo]},p{k},{x},{y}\n" for k, (x, y) in enumerate(px) if k != 5)
    )  # p5 not labelled
    return obj, labels, points, px


def test_natural_labels_become_infer_points_of_a_natural_frame(rendered, tmp_path):
    folder, truth = rendered
    obj_path, labels_path, points, px = _natural_files(tmp_path, truth, 2, np.random.default_rng(0))
    obj = read_object(obj_path)
    result = ingest(
        [folder / str(truth.frame_id[2]), folder / str(truth.frame_id[4])],
        paper_rig(),
        obj=obj,
        labels=read_labels(labels_path, obj),
    )
    ds = result.dataset
    assert ds.n_points == 320 + 12 and ds.meta["object_points"] == [f"p{k}" for k in range(12)]
    assert list(ds.scene) == ["natural", "rig"] and ds.split[0] == "test"
    labelled = np.r_[np.zeros(320, bool), np.arange(12) != 5]
    np.testing.assert_array_equal(ds.infer_mask[0], labelled)
    assert ds.valid[0, :320].sum() >= 160 and np.array_equal(ds.valid[0, 320:], labelled[320:])
    np.testing.assert_allclose(ds.points_2d[0, 320:][labelled[320:]], px[labelled[320:]])
    np.testing.assert_allclose(ds.points_3d[0, 320:][labelled[320:]], points[labelled[320:]])
    np.testing.assert_array_equal(ds.infer_mask[1], ds.valid[1])
    assert not ds.valid[1, 320:].any()
    assert report(result, paper_rig())["photos"][0]["labels"] == 11


@pytest.mark.parametrize(
    "which, text, words",
    [
        ("object", "id,X_mm,Y_mm,Z_mm\np0,1,2,3\n", "object.csv:1: the header must be point_id,X_mm,Y_mm,Z_mm"),
        ("object", "point_id,X_mm,Y_mm,Z_mm\np0,1,2\n", "object.csv:2: expected 4 fields"),
        ("object", "point_id,X_mm,Y_mm,Z_mm\np0,1,2,3\np0,4,5,6\n", "object.csv:3: duplicate point_id 'p0'"),
        ("object", "point_id,X_mm,Y_mm,Z_mm\np0,1,nan,3\n", "object.csv:2: Y_mm must be a finite number"),
        ("labels", "image,point_id,x_px,y_px\na.jpg,p9,1,2\n", "labels.csv:2: point_id 'p9' is not in the object file"),
        ("labels", "image,point_id,x_px,y_px\na.jpg,p0,1,2\na.jpg,p0,3,4\n", "labels.csv:3: point 'p0' labelled twice"),
        ("labels", "image,point_id,x_px,y_px\na.jpg,p0,one,2\n", "labels.csv:2: x_px must be a finite number"),
        ("labels", "image,point_id,x_px,y_px\n", "labels.csv: no rows after the header"),
    ],
)
def test_bad_csv_raises_labels_error_naming_file_and_line(tmp_path, which, text, words):
    obj, labels = tmp_path / "object.csv", tmp_path / "labels.csv"
    obj.write_text(text if which == "object" else "point_id,X_mm,Y_mm,Z_mm\np0,1,2,3\n")
    labels.write_text(text)
    with pytest.raises(LabelsError) as exc:
        read_labels(labels, read_object(obj))
    assert words in str(exc.value)


def test_bad_inputs_raise_typed_errors(rendered, tmp_path):
    folder, truth = rendered
    photo = folder / str(truth.frame_id[0])
    with pytest.raises(IngestError, match="no such photo"):
        ingest([tmp_path / "missing.jpg"], paper_rig())
    twin = tmp_path / photo.name
    twin.write_bytes(photo.read_bytes())
    with pytest.raises(IngestError, match="two photos are named photo-0000.jpg"):
        ingest([photo, twin], paper_rig())
    obj_path, labels_path, _, _ = _natural_files(tmp_path, truth, 2, np.random.default_rng(1))
    obj = read_object(obj_path)
    with pytest.raises(LabelsError, match="labels for photo-0002.jpg, which is not among the photos"):
        ingest([photo], paper_rig(), obj=obj, labels=read_labels(labels_path, obj))
    text = tmp_path / "notes.heic"
    text.write_text("not an image")
    with pytest.raises(PhotoError, match="notes.heic: unsupported image format"):
        read_photo(text)
    with pytest.raises(PhotoError, match="missing.jpg: cannot read"):
        read_photo(tmp_path / "missing.jpg")


def _with_exif_orientation(jpeg: bytes, orientation: int, order: str) -> bytes:
    """The JPEG with an APP1 Exif segment holding one IFD0 entry: Orientation (SHORT)."""
    tag = b"II" if order == "little" else b"MM"
    entry = (
        (0x0112).to_bytes(2, order)
        + (3).to_bytes(2, order)
        + (1).to_bytes(4, order)
        + orientation.to_bytes(2, order)
        + b"\0\0"
    )
    tiff = tag + (42).to_bytes(2, order) + (8).to_bytes(4, order) + (1).to_bytes(2, order) + entry + b"\0\0\0\0"
    payload = b"Exif\0\0" + tiff
    return jpeg[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + jpeg[2:]


def test_exif_orientation_is_reported_not_applied(rendered, tmp_path):
    folder, truth = rendered
    original = folder / str(truth.frame_id[0])
    turned = tmp_path / "turned.jpg"
    turned.write_bytes(_with_exif_orientation(original.read_bytes(), 6, "little"))
    photo = read_photo(turned)
    assert photo.exif_orientation == 6
    np.testing.assert_array_equal(photo.gray, read_photo(original).gray)  # pixels as the sensor stored them
    assert exif_orientation(_with_exif_orientation(original.read_bytes(), 3, "big")) == 3
    assert read_photo(original).exif_orientation == 1
    rep = report(ingest([turned], paper_rig()), paper_rig())
    assert rep["photos"][0]["exif_orientation"] == 6 and rep["photos"][0]["skipped"] is None


def test_a_board_cut_by_the_image_edge_is_dropped_not_faked(rendered):
    folder, truth = rendered
    gray = cv2.imread(str(folder / str(truth.frame_id[0])), cv2.IMREAD_GRAYSCALE)
    corners = truth.corners_px[0].reshape(4, 80, 2)
    cut = int(np.median(corners[0, :, 0]))  # through the middle of board 0's corners
    crop = np.ascontiguousarray(gray[:, cut:])
    detections = detect_boards(crop, paper_rig()).detections
    truth_px = corners - [cut, 0]
    assert len(detections) >= 2
    for d in detections:  # every detection is a whole board, exactly where a true board lies (either way round)
        assert (
            min(
                board_rms(d.corners_px[perm], truth_px[b])
                for b in range(4)
                for perm in (np.arange(80), np.arange(80)[::-1])
            )
            < 0.3
        )


def _synthetic_detections(rig: Rig, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, rng) -> list[Detection]:
    """Every board's projected corners (+0.1 px noise), some turned 180° (as a plain-board detector may
    report them), in shuffled order."""
    px = project(rig.points(), K, rvec, tvec) + rng.normal(0, 0.1, (rig.n_points, 2))
    dets = [
        Detection(b.inner_corners, px[rig.board_of_point == k][:: 1 if k % 2 else -1]) for k, b in enumerate(rig.boards)
    ]
    return [dets[i] for i in rng.permutation(len(dets))]


def test_identify_tells_identical_boards_apart_and_rejects_a_symmetric_rig():
    rng = np.random.default_rng(3)
    K = np.array([[3050.0, 0, 2030.0], [0, 3050.0, 1500.0], [0, 0, 1]])
    rig = paper_rig()
    for roll in (0.1, np.pi + 0.1):  # upright and upside down
        R = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
        rvec, tvec = matrix_to_rvec(R), np.array([10.0, -20.0, 600.0])
        dets = _synthetic_detections(rig, K, rvec, tvec, rng)
        found = identify(dets, rig, rough_k((4032, 3024)))
        np.testing.assert_allclose(found.corners_px, project(rig.points(), K, rvec, tvec), atol=0.5)
        assert np.abs(k_params(found.K) - k_params(K)).max() < 15 and found.rms_px < 0.2
    left = Board("left", (10, 8), 22.0, (0.0, 0.6, 0.0), (-260.0, -80.0, 0.0))
    R_half_turn = rvec_to_matrix(np.array([0.0, 0.0, np.pi]))
    right = dataclasses.replace(
        left,
        name="right",
        rvec=tuple(matrix_to_rvec(R_half_turn @ left.rotation())),
        tvec_mm=tuple(R_half_turn @ np.array(left.tvec_mm)),
    )
    symmetric = Rig((left, right))  # looks the same turned half round: no photo can tell its boards apart
    dets = _synthetic_detections(symmetric, K, np.array([0.1, 0.05, 0.0]), np.array([0.0, 0.0, 700.0]), rng)
    with pytest.raises(IdentificationError, match="ambiguous board identity"):
        identify(dets, symmetric, rough_k((4032, 3024)))


@pytest.fixture(scope="module")
def charuco_rendered(tmp_path_factory):
    rig = Rig(
        tuple(
            dataclasses.replace(b, aruco=Aruco("DICT_4X4_250", 49 * k, 16.0)) for k, b in enumerate(paper_rig().boards)
        )
    )
    folder = tmp_path_factory.mktemp("charuco")
    write_render(folder, rig, scaled_profile(get_profile("galaxy-s8"), SCALE), 5, seed=0)
    return rig, folder, read_truth(folder / TRUTH_FILE)


def test_charuco_boards_are_identified_by_their_markers_even_partly_hidden(charuco_rendered):
    rig, folder, truth = charuco_rendered
    result = ingest([folder / str(f) for f in truth.frame_id], rig)
    s = score(result.dataset, truth)
    assert s.detection_rate >= 0.95 and s.identity_errors == 0 and s.corner_rms_px <= 0.15
    gray = cv2.imread(str(folder / str(truth.frame_id[0])), cv2.IMREAD_GRAYSCALE)
    b = int(np.flatnonzero(truth.seen[0].reshape(4, 80).all(1))[0])
    true_px = truth.corners_px[0, 80 * b : 80 * b + 80]
    cut = np.median(true_px[:, 0])
    hidden = true_px[:, 0] < cut  # paint over these corners and the squares around them
    hull = cv2.convexHull(np.float32(true_px[hidden])).astype(np.int32)
    cv2.fillConvexPoly(gray, hull, 90)
    cv2.polylines(gray, [hull], True, 90, thickness=int(0.6 * np.linalg.norm(true_px[1] - true_px[0])))
    partial = {d.board: d for d in detect_boards(gray, rig).detections}[b]
    found = np.isfinite(partial.corners_px[:, 0])
    assert 10 < found.sum() < 80 and not (found & hidden).any()  # the markers still seen vouch for their corners
    assert np.abs(partial.corners_px[found] - true_px[found]).max() < 0.5
