"""`dimenet ingest` on real photographs: ../shared/real-photos/ortho (from the project's root).

Four 1600x1200 photos of a real rig of three orthogonal checkerboards (a 6x7 floor, two 8x6 walls,
28 mm squares; rig.json), from the two cameras of a stereo pair: left.jpg / right.jpg with painted
separators between the boards, left_calib.jpg / right_calib.jpg the same views without them (the
boards meet at the folds). Every photo must be accepted with its three boards; our corners must be
OpenCV's own (``cv2.findChessboardCornersSB`` with the flags that find the board), and each photo's
K* (``evaluation.calibration``) OpenCV's single-view fit of the same corners (``cv2.calibrateCamera``,
pinhole, no distortion), beside the K the folder's README publishes. The figures are in
models_spec/ingest.md ("Real photos").
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.formats.rig import load_rig
from dimenet.runtime.geometry import k_params
from dimenet.runtime.ingest.outcome import IDENTIFIED
from dimenet.runtime.ingest.pipeline import ingest, report

ROOT = Path(__file__).resolve().parents[2]
ORTHO = ROOT.parent / "shared" / "real-photos" / "ortho"
PHOTOS = ("left.jpg", "right.jpg", "left_calib.jpg", "right_calib.jpg")
PUBLISHED_K = {"left": (1649.4, 1654.1, 793.3, 614.4), "right": (1631.7, 1625.7, 789.1, 634.8)}  # README, DLT
SB_FLAGS = (
    0,
    cv2.CALIB_CB_NORMALIZE_IMAGE,
    cv2.CALIB_CB_EXHAUSTIVE,
    cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE,
)
ALONE_MARGIN = 0.6  # squares beyond a board's corners kept when it is shown to OpenCV alone (the rest grey)

pytestmark = pytest.mark.skipif(
    not all((ORTHO / name).is_file() for name in (*PHOTOS, "rig.json")),
    reason=f"the real photos are not there: {ORTHO} (../shared/real-photos/ortho from the project root)",
)


@pytest.fixture(scope="module")
def rig():
    return load_rig(ORTHO / "rig.json")


@pytest.fixture(scope="module")
def ingested(rig):
    return ingest([ORTHO / name for name in PHOTOS], rig, split="train")


def board_slices(rig) -> list[slice]:
    start = np.r_[0, np.cumsum([b.n_points for b in rig.boards])]
    return [slice(int(a), int(b)) for a, b in zip(start[:-1], start[1:])]


def alone(gray: np.ndarray, corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """The photo with everything but the board (ALONE_MARGIN squares beyond its corners) painted grey."""
    nx, ny = pattern
    grid = np.stack(np.meshgrid(np.arange(nx), np.arange(ny)), -1).reshape(-1, 2).astype(np.float64)
    H = cv2.findHomography(grid, corners_px)[0]
    m = ALONE_MARGIN
    box = np.array([[-m, -m], [nx - 1 + m, -m], [nx - 1 + m, ny - 1 + m], [-m, ny - 1 + m]]).reshape(-1, 1, 2)
    keep = np.zeros_like(gray)
    cv2.fillConvexPoly(keep, np.round(cv2.perspectiveTransform(box, H).reshape(-1, 2)).astype(np.int32), 255)
    return np.where(keep > 0, gray, 128).astype(np.uint8)


def opencv_corners(image: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """(n, 2) px OpenCV's findChessboardCornersSB corners with the first of SB_FLAGS that finds the board."""
    for flags in SB_FLAGS:
        ok, corners = cv2.findChessboardCornersSB(image, pattern, flags=flags)
        if ok:
            return corners.reshape(-1, 2).astype(np.float64)
    raise AssertionError(f"OpenCV finds no {pattern} board with any of the flags {SB_FLAGS}")


def matched(theirs: np.ndarray, ours: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """OpenCV's corners in our order: turned 0° or 180° (a plain board's detector order), whichever is closer."""
    nx, ny = pattern
    idx = np.arange(nx * ny).reshape(ny, nx)
    return min((theirs[np.rot90(idx, k).ravel()] for k in (0, 2)), key=lambda c: np.abs(c - ours).max())


def test_every_real_photo_is_accepted_with_its_three_boards_identified(ingested, rig):
    rep = report(ingested, rig)
    assert rep["totals"]["frames"] == 4 and rep["totals"]["skipped"] == 0
    for p in rep["photos"]:
        assert p["skipped"] is None, (p["photo"], p["skipped"])
        assert sorted(p["boards"]) == ["floor", "left-wall", "right-wall"] and p["corners"] == 42 + 48 + 48
        assert [b["status"] for b in p["board_lines"]] == [IDENTIFIED] * 3
        assert all(b["residual_px"] <= b["tolerance_px"] for b in p["board_lines"])
        assert p["rms_px"] < 2.5 and p["runner_up_rms_px"] > 3 * p["rms_px"]
        # one board found by a detector, the other two refined where its one-plane camera puts them
        placed = [b for b in p["board_lines"] if b["found_by"].startswith("refined where the first board's camera")]
        assert len(placed) == 2, [b["found_by"] for b in p["board_lines"]]


def test_our_corners_are_opencvs_findchessboardcornerssb_on_each_board(ingested, rig):
    ds = ingested.dataset
    for f, name in enumerate(ds.frame_id):
        gray = cv2.imread(str(ORTHO / name), cv2.IMREAD_GRAYSCALE)
        for board, sl in zip(rig.boards, board_slices(rig)):
            ours = ds.points_2d[f, sl]
            assert ds.valid[f, sl].all(), (name, board.name)
            theirs = matched(
                opencv_corners(alone(gray, ours, board.inner_corners), board.inner_corners), ours, board.inner_corners
            )
            raw = np.linalg.norm(theirs - ours, axis=1)
            assert np.median(raw) < 1.0, (name, board.name, raw)  # the same board, in the rig's corner order
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.001)
            refined = cv2.cornerSubPix(gray, theirs.astype(np.float32).reshape(-1, 1, 2), (7, 7), (-1, -1), criteria)
            assert np.abs(refined.reshape(-1, 2) - ours).max() < 0.3, (name, board.name)  # and OpenCV's refinement


def test_painted_separators_do_not_move_the_corners(ingested):
    ds = ingested.dataset
    rows = {str(name): k for k, name in enumerate(ds.frame_id)}
    for view in ("left", "right"):  # the same camera and pose with and without the separators
        np.testing.assert_allclose(ds.points_2d[rows[f"{view}.jpg"]], ds.points_2d[rows[f"{view}_calib.jpg"]], atol=0.5)


def test_k_star_of_each_photo_is_opencvs_single_view_fit_of_the_same_corners(ingested):
    ds = ingested.dataset
    K_star = k_params(calibrate_dataset(ds).K_star)
    h, w = (1200, 1600)
    pinhole = (
        cv2.CALIB_USE_INTRINSIC_GUESS  # a non-planar view needs a start
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K1
        | cv2.CALIB_FIX_K2
        | cv2.CALIB_FIX_K3
        | cv2.CALIB_FIX_K4
        | cv2.CALIB_FIX_K5
        | cv2.CALIB_FIX_K6
    )
    for f, name in enumerate(ds.frame_id):
        v = ds.valid[f]
        K0 = np.array([[0.75 * w, 0, (w - 1) / 2], [0, 0.75 * w, (h - 1) / 2], [0, 0, 1]])
        _, K, _, _, _ = cv2.calibrateCamera(
            [ds.points_3d[f][v].astype(np.float32)],
            [ds.points_2d[f][v].astype(np.float32)],
            (w, h),
            K0,
            np.zeros(5),
            flags=pinhole,
        )
        theirs = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        camera = Path(str(name)).stem.split("_")[0]  # left_calib.jpg: the left camera
        for reference in (theirs, np.array(PUBLISHED_K[camera])):
            assert np.all(np.abs(K_star[f, :2] - reference[:2]) <= 0.02 * reference[:2]), (name, K_star[f], reference)
            assert np.all(np.abs(K_star[f, 2:] - reference[2:]) <= 25.0), (name, K_star[f], reference)


def test_the_rig_at_640x480_gives_every_board_of_every_photo_from_its_first(tmp_path):
    """Reduced to 640x480 the walls' squares are ~11 px: the whole-photo detectors find one board on each photo,
    slowly or not at all after it. The camera of that board (its one-plane K held, posed on it and the next
    board) puts the third within the look's tolerance, where a K refitted freely on two planes does not on the
    right camera's photos: every photo gives its three boards from one detector call."""
    small = []
    for name in PHOTOS:
        image = cv2.resize(cv2.imread(str(ORTHO / name)), (640, 480), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(tmp_path / name), image, [cv2.IMWRITE_JPEG_QUALITY, 92])
        small.append(tmp_path / name)
    result = ingest(small, load_rig(ORTHO / "rig.json"), split="train")
    for photo in result.results:
        assert photo.skipped is None and photo.boards == (0, 1, 2), (photo.name, photo.skipped)
        assert photo.rms_px < 1.0
        how = [line.found_by or "" for line in photo.board_lines]
        placed = [f for f in how if "first board's camera" in f]
        assert len(placed) == 2 and sum("findChessboard" in f for f in how) == 1, (photo.name, how)
