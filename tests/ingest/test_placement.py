"""Placing the rig's boards from the first one found: its one-plane camera, the corners refined where it puts them;
and looking again where the photo's camera puts a board not found (``predicted.search_predicted``).

Rendered photos of the paper rig (four identical 10x8 boards) at 1/3 of the Galaxy S8's 4032x3024 px;
the renderer's truth says where every corner is.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import Board, Rig, paper_rig
from dimenet.runtime.geometry import k_params
from dimenet.runtime.ingest import detection, predicted
from dimenet.runtime.ingest.detection import (
    PLACE_TOLERANCE,
    SEED_STEPS,
    STEPS,
    boards_meet,
    confirm,
    detect_boards,
    seed_steps,
)
from dimenet.runtime.ingest.grid import corner_spacing, fit_model
from dimenet.runtime.ingest.outcome import IDENTIFIED
from dimenet.runtime.ingest.pipeline import ingest
from dimenet.runtime.ingest.placement import one_plane_k, place
from dimenet.runtime.ingest.predicted import search_predicted
from dimenet.runtime.ingest.refine import SUBPIX_WINDOW_PX, colouring
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, scaled_profile, write_render

SCALE = 3.0  # 1344 x 1008 px
PHOTO = 0  # upright, no board covered: all four shown


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    folder = tmp_path_factory.mktemp("place")
    write_render(folder, paper_rig(), scaled_profile(get_profile("galaxy-s8"), SCALE), 3, seed=0)
    truth = read_truth(folder / TRUTH_FILE)
    return folder, truth


@pytest.fixture(scope="module")
def photo(rendered):
    folder, truth = rendered
    gray = cv2.imread(str(folder / truth.frame_id[PHOTO]), cv2.IMREAD_GRAYSCALE)
    seeds = []
    detect_boards(gray, paper_rig(), lambda d: seeds.append(d) or ())  # the first board kept, nothing placed
    return gray, truth.corners_px[PHOTO].reshape(4, 80, 2), truth.K[PHOTO], seeds[0]


def truth_board(corners_px: np.ndarray, truth_boards: np.ndarray) -> int:
    """The board whose true corners these are, in any order (each within 0.15 px of one), or -1."""
    for b, true_px in enumerate(truth_boards):
        nearest = np.linalg.norm(corners_px[:, None] - true_px[None], axis=2).min(1)
        if np.all(nearest <= 0.15):
            return b
    return -1


def test_truth_shows_all_four_boards(rendered):
    _, truth = rendered
    assert truth.seen[PHOTO].all() and not truth.upside_down[PHOTO] and truth.covered_board[PHOTO] < 0


def test_one_boards_homography_gives_the_focal_length_within_a_few_percent(photo):
    gray, _, K_true, seed = photo
    size = (gray.shape[1], gray.shape[0])
    K = one_plane_k(fit_model(seed.corners_px, seed.grid_shape, size, seed.k).H, size)
    assert abs(K[0, 0] / K_true[0, 0] - 1) < 0.05 and K[0, 0] == K[1, 1]
    np.testing.assert_allclose(k_params(K)[2:], [(size[0] - 1) / 2, (size[1] - 1) / 2])


def test_place_finds_the_other_boards_at_their_true_corners(photo):
    gray, truth_boards, _, seed = photo
    placed = place(gray, paper_rig(), seed)
    boards = sorted(truth_board(d.corners_px, truth_boards) for d in placed)
    seed_board = truth_board(seed.corners_px, truth_boards)
    assert seed_board >= 0 and boards == sorted(set(range(4)) - {seed_board})
    assert all("refined where the first board's camera" in d.found_by for d in placed)


def test_place_confirms_nothing_where_the_other_boards_are_painted_out(photo):
    gray, truth_boards, _, seed = photo
    blank = gray.copy()
    for b, true_px in enumerate(truth_boards):
        if b != truth_board(seed.corners_px, truth_boards):
            hull = cv2.convexHull(np.round(true_px).astype(np.int32))
            cv2.fillConvexPoly(blank, cv2.convexHull(hull), 200)  # a flat grey board: no corners
            cv2.polylines(blank, [hull], True, 0, 9)  # with a dark outline, edges but no checker corners
    assert place(blank, paper_rig(), seed) == ()


def test_confirm_refines_a_board_put_a_fraction_of_a_square_off_and_refuses_one_off_by_half(photo):
    gray, truth_boards, _, seed = photo
    size = (gray.shape[1], gray.shape[0])
    contrast = colouring(gray, fit_model(seed.corners_px, seed.grid_shape, size, seed.k), seed.grid_shape).contrast
    true_px = truth_boards[(truth_board(seed.corners_px, truth_boards) + 1) % 4]
    spacing = corner_spacing(true_px, (10, 8))
    step = (true_px[1] - true_px[0]) / np.linalg.norm(true_px[1] - true_px[0])  # along the board's rows
    near = confirm(gray, true_px + 0.2 * spacing * step, (10, 8), seed.k, contrast)
    assert near is not None and np.abs(near - true_px).max() < 0.15
    assert confirm(gray, true_px + 0.5 * spacing * step, (10, 8), seed.k, contrast) is None
    assert 0.5 > PLACE_TOLERANCE > 0.25  # between the quarter square a one-plane camera errs and a neighbour's


def test_ingest_places_boards_and_still_finds_identifies_them_all(rendered):
    folder, truth = rendered
    result = ingest([folder / str(f) for f in truth.frame_id], paper_rig())
    lines = [line for r in result.results for line in r.board_lines if line.status == IDENTIFIED]
    placed = [line for line in lines if "refined where the first board's camera" in (line.found_by or "")]
    assert len(lines) == int(truth.seen.reshape(3, 4, 80).all(2).sum()) and placed


def test_confirm_reaches_a_corner_put_beyond_refines_window_at_12_mp(photo):
    # The photo at 3x (4032 px wide, ~105 px squares): put 0.2 of a square (~21 px) off, the corners lie
    # beyond refine's largest half-window (12 px); confirm's window must still hold them, or they stay put.
    gray, truth_boards, _, seed = photo
    big = cv2.resize(gray, None, fx=3, fy=3, interpolation=cv2.INTER_CUBIC)
    true_px = 3 * (truth_boards[(truth_board(seed.corners_px, truth_boards) + 1) % 4] + 0.5) - 0.5
    spacing = corner_spacing(true_px, (10, 8))
    assert 0.2 * spacing > SUBPIX_WINDOW_PX[1]
    step = (true_px[1] - true_px[0]) / np.linalg.norm(true_px[1] - true_px[0])
    size = (big.shape[1], big.shape[0])
    seed_px = 3 * (seed.corners_px + 0.5) - 0.5
    contrast = colouring(big, fit_model(seed_px, seed.grid_shape, size), seed.grid_shape).contrast
    found = confirm(big, true_px + 0.2 * spacing * step, (10, 8), (0.0, 0.0), contrast)
    assert found is not None and np.abs(found - true_px).max() < 0.5


@pytest.fixture
def steps_called(monkeypatch):
    """The detector steps ``find_one`` is called with, in order."""
    called = []
    find_one = detection.find_one
    for module in (detection, predicted):  # the first search and the search again
        monkeypatch.setattr(
            module, "find_one", lambda copy, pattern, step: called.append(step) or find_one(copy, pattern, step)
        )
    return called


def other_board(photo) -> tuple[int, np.ndarray]:
    """A board other than the seed: its rig index and true corners (80, 2) px."""
    _, truth_boards, _, seed = photo
    b = (truth_board(seed.corners_px, truth_boards) + 1) % 4
    return b, truth_boards[b]


def test_search_predicted_keeps_a_board_where_the_camera_puts_it_with_no_detector_call(photo, steps_called):
    gray, _, _, seed = photo
    b, true_px = other_board(photo)
    spacing = corner_spacing(true_px, (10, 8))
    found = search_predicted(gray, paper_rig(), (seed,), {b: true_px + 0.1 * spacing})
    assert len(found.detections) == 1 and not found.dropped and steps_called == []
    assert np.abs(found.detections[0].corners_px - true_px).max() < 0.15
    assert "where the photo's camera puts" in found.detections[0].found_by


def test_search_predicted_runs_only_the_first_step_on_a_partly_hidden_board(photo, steps_called):
    gray, _, _, seed = photo
    b, true_px = other_board(photo)
    covered = gray.copy()
    left = true_px.reshape(8, 10, 2)[:, :5].reshape(-1, 2)  # half its columns under a flat grey card
    cv2.fillConvexPoly(covered, cv2.convexHull(np.round(left).astype(np.int32)), 128)
    found = search_predicted(covered, paper_rig(), (seed,), {b: true_px})
    assert found.detections == () and steps_called and set(steps_called) == {STEPS[0]}
    ((board, why),) = found.hidden
    assert board == b and why.startswith("hidden: ") and 0 < int(why.split()[1]) <= 40  # of the 40 covered


def test_search_predicted_runs_every_step_where_no_corner_of_the_board_shows(photo, steps_called):
    gray, _, _, seed = photo
    b, true_px = other_board(photo)
    blank = gray.copy()
    cv2.fillConvexPoly(blank, cv2.convexHull(np.round(true_px).astype(np.int32)), 128)
    found = search_predicted(blank, paper_rig(), (seed,), {b: true_px})
    assert found.detections == () and set(steps_called) == set(STEPS) and [k for k, _ in found.hidden] == [b]


def test_search_predicted_looks_for_no_board_on_a_board_kept(photo, steps_called):
    # A camera that puts another board onto the seed (a wrong labelling): its corners are the seed's, which the
    # look would confirm; the board is looked for only by the detectors, with the seed masked out.
    gray, _, _, seed = photo
    b, _ = other_board(photo)
    found = search_predicted(gray, paper_rig(), (seed,), {b: seed.corners_px[:80]})
    assert found.detections == () and steps_called


def test_the_seed_asks_larger_first_only_on_a_rig_whose_boards_meet():
    # The real three-plane rig's floor and a wall: their inner corners 1.41 squares apart across the fold.
    floor = Board("floor", (6, 7), 28.0, (2.221441469079183, 2.221441469079183, 0.0), (28.0, 28.0, 0.0))
    wall = Board("wall", (8, 6), 28.0, (1.5707963267948966, 0.0, 0.0), (28.0, 0.0, 28.0))
    assert boards_meet(Rig((floor, wall))) and seed_steps(Rig((floor, wall))) == SEED_STEPS[::-1]
    assert seed_steps(Rig((floor, wall)))[0].flags & cv2.CALIB_CB_LARGER
    away = Board("wall", (8, 6), 28.0, wall.rvec, (28.0, -28.0, 28.0))  # a square further off: 2.24 squares
    assert not boards_meet(Rig((floor, away))) and seed_steps(Rig((floor, away))) == SEED_STEPS
    assert not boards_meet(paper_rig()) and seed_steps(paper_rig())[0].detector == "classic"


@pytest.mark.parametrize(("gap_mm", "meet"), [(20.0, True), (25.0, False)])
def test_boards_meet_measures_large_boards_side_by_side_in_bounded_memory(gap_mm, meet):
    # Two 1000 x 40 boards (40,000 corners each: all pairs of them would take 38 GB), side by side in one plane.
    a = Board("a", (1000, 40), 10.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    b = Board("b", (1000, 40), 10.0, (0.0, 0.0, 0.0), (0.0, 390.0 + gap_mm, 0.0))
    assert boards_meet(Rig((a, b))) == meet  # 2 squares between inner corners: no white margin between them
