"""The board model (homography + radial distortion), the acceptance test, grid growth and the per-board outcome.

Synthetic checkerboard images (drawn by a homography) and one rendered photo of the paper rig at 1/3 of
4032x3024 px; the measurements on real photos behind the tolerances are in models_spec/ingest.md.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import paper_rig
from dimenet.runtime.ingest.detection import BoardSearch, Detection, Dropped
from dimenet.runtime.ingest.grid import (
    BoardModel,
    corner_spacing,
    fit_model,
    grid_points,
    placements,
    residuals,
)
from dimenet.runtime.ingest.outcome import DROPPED, FOUND, NOT_FOUND, board_lines, shortfall
from dimenet.runtime.ingest.refine import ACCEPT_TOLERANCE, grow, judged, refine_plain
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, scaled_profile, write_render

SIZE = (4032, 3024)  # width, height px


def projected_board(k1: float) -> np.ndarray:
    """(80, 2) px a 10x8, 22 mm board 400 mm away, tilted, through a 4032x3024 lens of OpenCV radial k1."""
    K = np.array([[3000.0, 0, 2015.5], [0, 3000.0, 1511.5], [0, 0, 1]])
    local = paper_rig().boards[0].local_points()
    points = local - local.mean(0)
    px = cv2.projectPoints(
        points, np.array([0.7, 0.3, 0.1]), np.array([150.0, 100.0, 400.0]), K, np.array([k1, 0, 0, 0])
    )
    return px[0].reshape(-1, 2)


def homography_residual(corners_px: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    grid = grid_points(pattern)
    H = cv2.findHomography(grid, corners_px, 0)[0]
    return np.linalg.norm(cv2.perspectiveTransform(grid.reshape(-1, 1, 2), H).reshape(-1, 2) - corners_px, axis=1)


def test_the_board_model_absorbs_a_lens_barrel_distortion_that_a_homography_cannot():
    corners = projected_board(-0.1)  # a phone main camera's order of barrel distortion
    assert homography_residual(corners, (10, 8)).max() > 5.0
    model = fit_model(corners, (10, 8), SIZE)
    assert residuals(corners, model, (10, 8)).max() < 1.0 and model.k[0] < 0
    assert residuals(projected_board(0.0), fit_model(projected_board(0.0), (10, 8), SIZE), (10, 8)).max() < 1e-3
    m = BoardModel(np.eye(3), (-0.08, 0.0), np.array([2015.5, 1511.5]), 2016.0)
    np.testing.assert_allclose(m.distort(m.undistort(corners)), corners, atol=1e-9)


def strong_lens_board() -> np.ndarray:
    """(54, 2) px a 9x6, 25 mm board 250-340 mm away in the bottom-left corner of a 640x480 image, through a wide
    lens (f = 400 px) of OpenCV radial k1 = -0.3, k2 = 0.1, k3 = -0.02 (models_spec/ingest.md, "Acceptance")."""
    K = np.array([[400.0, 0, 319.5], [0, 400.0, 233.0], [0, 0, 1]])
    points = np.hstack([grid_points((9, 6)) * 25.0, np.zeros((54, 1))])
    lens = np.array([-0.3, 0.1, 0, 0, -0.02])
    px = cv2.projectPoints(points, np.array([0.3, -0.4, 0.1]), np.array([-256.7, 107.1, 243.5]), K, lens)
    return px[0].reshape(-1, 2)


def test_a_strong_lens_is_judged_by_two_terms_and_a_misplaced_corner_still_refused():
    corners, size = strong_lens_board(), (640, 480)
    tolerance = ACCEPT_TOLERANCE * corner_spacing(corners, (9, 6))
    assert residuals(corners, fit_model(corners, (9, 6), size), (9, 6)).max() > 1.1 * tolerance  # one term: 14 %
    model, worst, tol = judged(corners, (9, 6), size)
    assert tol == pytest.approx(tolerance) and worst < 0.6 * tol and model.k[1] != 0  # two terms: 6 %, held out 9 %
    np.testing.assert_allclose(model.distort(model.undistort(corners)), corners, atol=1e-6)
    for i, step in ((53, (0.3, 0.0)), (22, (0.0, 0.3)), (0, (-0.2, -0.2))):  # the outermost, a middle, the first
        moved = corners.copy()
        moved[i] += np.array(step) * corner_spacing(corners, (9, 6))
        _, worst, tol = judged(moved, (9, 6), size)
        assert worst > tol


def checkerboard(squares: tuple[int, int], square_px: int = 40, margin_px: int = 60) -> np.ndarray:
    """A grey image of a checkerboard of (columns, rows) squares on white, its first square black."""
    cols, rows = squares
    img = np.full((rows * square_px + 2 * margin_px, cols * square_px + 2 * margin_px), 235, np.uint8)
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 0:
                y, x = margin_px + r * square_px, margin_px + c * square_px
                img[y : y + square_px, x : x + square_px] = 20
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def inner_corners(squares: tuple[int, int], square_px: int = 40, margin_px: int = 60) -> np.ndarray:
    """(nx·ny, 2) px the inner corners of ``checkerboard`` (pixel centres at integers), row by row."""
    cols, rows = squares
    j, i = np.mgrid[1:rows, 1:cols]
    return np.stack([margin_px + i.ravel() * square_px - 0.5, margin_px + j.ravel() * square_px - 0.5], 1).astype(float)


def test_a_grid_grows_to_where_the_pattern_runs_on_and_no_further():
    img = checkerboard((11, 9))  # 10 x 8 inner corners
    full = inner_corners((11, 9)).reshape(8, 10, 2)
    window = full[1:7, 1:9].reshape(-1, 2)  # an 8 x 6 window of it, as a detector asked for (8, 6) may return
    corners, grid = grow(img, window, (8, 6), (0.0, 0.0))
    assert grid == (10, 8)
    np.testing.assert_allclose(corners, full.reshape(-1, 2), atol=0.2)
    exact = checkerboard((9, 7))  # a board of just the pattern: white paper beyond its outer squares
    corners, grid = grow(exact, inner_corners((9, 7)), (8, 6), (0.0, 0.0))
    assert grid == (8, 6)


def test_placements_put_a_rig_pattern_at_every_turn_and_offset_of_a_grown_grid():
    assert len(placements((8, 6), (8, 6))) == 2  # 0° and 180°
    assert len(placements((5, 5), (5, 5))) == 4  # and 90°, 270° for a square grid
    assert len(placements((9, 7), (8, 6))) == 8  # 2 x 2 offsets, 0° and 180°
    assert len(placements((6, 9), (8, 6))) == 4  # turned a quarter, 2 offsets each way round
    assert placements((8, 6), (9, 6)) == []
    first = placements((9, 7), (8, 6))[0]
    np.testing.assert_array_equal(first.reshape(6, 8), np.arange(63).reshape(7, 9)[:6, :8])


@pytest.fixture(scope="module")
def paper_photo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("paper_shot")
    write_render(folder, paper_rig(), scaled_profile(get_profile("galaxy-s8"), 3.0), 1, seed=0)
    truth = read_truth(folder / TRUTH_FILE)
    return cv2.imread(str(folder / "photo-0000.jpg"), cv2.IMREAD_GRAYSCALE), truth


def test_a_board_is_kept_and_a_misplaced_corner_started_again(paper_photo):
    gray, truth = paper_photo
    shown = np.flatnonzero(truth.seen[0].reshape(4, 80).all(1))
    true_px = truth.corners_px[0].reshape(4, 80, 2)[shown[0]]
    start = true_px + np.random.default_rng(0).normal(0, 0.5, true_px.shape)
    start[79] += 0.45 * corner_spacing(true_px, (10, 8))  # the end of a row, misplaced by the detector
    refined = refine_plain(gray, start, (10, 8))
    assert refined.reason is None and refined.residual_px <= refined.tolerance_px
    assert np.abs(refined.corners_px - true_px).max() < 0.3


def test_a_grid_bent_over_two_boards_is_dropped_with_its_residual(paper_photo):
    gray, truth = paper_photo
    a, b = np.flatnonzero(truth.seen[0].reshape(4, 80).all(1))[:2]
    boards = truth.corners_px[0].reshape(4, 8, 10, 2)
    bent = np.concatenate([boards[a, :4], boards[b, :4]]).reshape(-1, 2)  # half of one board, half of another
    refined = refine_plain(gray, bent, (10, 8))
    assert refined.corners_px is None and refined.residual_px > refined.tolerance_px
    assert refined.tolerance_px == pytest.approx(ACCEPT_TOLERANCE * corner_spacing(bent, (10, 8)), rel=0.5)
    assert refined.reason == f"corner residual {refined.residual_px:.1f} px > {refined.tolerance_px:.1f} px tolerance"


def test_each_board_of_a_skipped_photo_has_its_line_and_the_message_counts_the_dropped():
    rig = paper_rig()
    kept = Detection((10, 8), np.zeros((80, 2)), found_by="findChessboardCorners at 1/4 size", residual_px=0.1)
    dropped = Dropped(
        (10, 8),
        "findChessboardCornersSB(EXHAUSTIVE) at 1/4 size",
        "corner residual 14.6 px > 5.2 px tolerance",
        14.6,
        5.2,
    )
    search = BoardSearch((kept,), (dropped,))
    lines = board_lines(rig, search)
    assert [line.status for line in lines] == [FOUND, DROPPED, NOT_FOUND, NOT_FOUND, NOT_FOUND]
    assert lines[1].why == dropped.reason and lines[1].found_by == dropped.found_by
    assert shortfall(search, 2, "a rig photo") == (
        "1 board(s) found, 1 more found by a detector but dropped (corner residual 14.6 px > 5.2 px tolerance), "
        "a rig photo needs 2"
    )
    identified = board_lines(rig, search, (2,), np.array([True, False, True, True]))
    assert [(line.status, line.board) for line in identified] == [
        ("identified", 2),
        (DROPPED, None),
        (NOT_FOUND, 0),
        (NOT_FOUND, 1),
        (NOT_FOUND, 3),
    ]
    assert identified[3].why == "not in view" and "in view" in identified[2].why
