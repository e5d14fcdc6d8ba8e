"""One printed checkerboard photographed from many views: a one-board rig, its photos planar frames.

The photos are rendered with the project's renderer (``write_render``; a one-board rig's view rule is its
board seen whole) at 1/3 of the Galaxy S8's 4032x3024 px; photos 1 and 6 are upside down (a one-board rig
has no covered photos). ``--min-boards`` moves the rule of a rig of several boards.
"""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import IngestError
from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import load_rig, paper_rig
from dimenet.runtime.ingest.pipeline import default_min_boards, ingest, report
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, scaled_profile, write_render

SCALE = 3.0  # 1344 x 1008 px
N_PHOTOS = 7
PATTERN = (9, 6)
ONE_BOARD = {
    "format": "dimenet-rig/1",
    "units": "mm",
    "boards": [
        {
            "name": "board",
            "inner_corners": list(PATTERN),
            "square_mm": 25.0,
            "rvec": [0.0, 0.0, 0.0],
            "tvec_mm": [-100.0, -62.5, 0.0],
            "aruco": None,
        }
    ],
}


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("rig") / "one_board.json"
    path.write_text(json.dumps(ONE_BOARD))
    return path


@pytest.fixture(scope="module")
def rendered(rig_file, tmp_path_factory):
    folder = tmp_path_factory.mktemp("one_board_shots")
    write_render(folder, load_rig(rig_file), scaled_profile(get_profile("galaxy-s8"), SCALE), N_PHOTOS, seed=0)
    return folder, read_truth(folder / TRUTH_FILE)


@pytest.fixture(scope="module")
def ingested(rig_file, rendered):
    folder, truth = rendered
    return ingest([folder / str(f) for f in truth.frame_id], load_rig(rig_file), split="train")


def turned(corners_px: np.ndarray, quarter_turns: int) -> np.ndarray:
    nx, ny = PATTERN
    return corners_px[np.rot90(np.arange(nx * ny).reshape(ny, nx), quarter_turns).ravel()]


def test_a_one_board_rig_renders_planar_views_with_no_covered_photo(rendered):
    folder, truth = rendered
    assert truth.seen.all() and (truth.covered_board == -1).all()
    assert np.flatnonzero(truth.upside_down).tolist() == [1, 6]
    assert cv2.imread(str(folder / truth.frame_id[0])).shape == (1008, 1344, 3)


def test_every_one_board_photo_is_a_planar_frame_with_the_true_corners(rig_file, rendered, ingested):
    folder, truth = rendered
    rig = load_rig(rig_file)
    assert default_min_boards(rig) == 1
    ds = ingested.dataset
    assert list(ds.frame_id) == list(truth.frame_id) and ds.valid.all()
    for f in range(ds.n_frames):
        r = ingested.results[f]
        assert r.boards == (0,) and r.K is None and r.rms_px is None
        # one plane tells no turn: the frame is labelled upright in the image, so an upside-down photo's
        # labelling is the board turned 180° (as valid a pose as the rig's own)
        truth_px = turned(truth.corners_px[f], 2 if truth.upside_down[f] else 0)
        error = np.linalg.norm(ds.points_2d[f] - truth_px, axis=1)
        assert np.sqrt(np.mean(error**2)) <= 0.1, (f, error.max())
    photo = report(ingested, rig)["photos"][0]
    assert photo["K_px"] is None and photo["rms_px"] is None and photo["board_lines"][0]["status"] == "identified"


def test_cli_ingests_one_board_photos_as_planar_frames(rig_file, rendered, tmp_path, capsys):
    folder, truth = rendered
    photos = [str(folder / str(f)) for f in truth.frame_id[:2]]
    out = tmp_path / "one.npz"
    assert main(["ingest", *photos, "--rig", str(rig_file), "--out", str(out), "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    assert "photo-0000.jpg  " in printed and "1 boards (board)  54 corners  planar (one board: no K)" in printed
    assert "2 frames" in printed
    assert main(["ingest", *photos, "--rig", str(rig_file), "--out", str(out), "--min-boards", "2"]) == 2
    assert "min_boards must be an integer from 1 to the rig's 1 boards, got 2" in capsys.readouterr().err


@pytest.fixture(scope="module")
def paper_photo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("paper_shot")
    write_render(folder, paper_rig(), scaled_profile(get_profile("galaxy-s8"), SCALE), 1, seed=0)
    return folder / "photo-0000.jpg", read_truth(folder / TRUTH_FILE)


def test_min_boards_one_on_a_rig_of_identical_boards_cannot_tell_one_board_apart(paper_photo, tmp_path):
    photo, truth = paper_photo
    corners = truth.corners_px[0].reshape(4, 80, 2)
    b = int(np.flatnonzero(truth.seen[0].reshape(4, 80).all(1))[0])
    square = np.linalg.norm(corners[b, 1] - corners[b, 0])
    x0, y0 = np.maximum(corners[b].min(0) - 1.5 * square, 0).astype(int)
    x1, y1 = (corners[b].max(0) + 1.5 * square).astype(int)
    gray = cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)
    crop = tmp_path / "one-board.png"
    cv2.imwrite(str(crop), gray[y0:y1, x0:x1])  # only board b whole (its neighbours cut by the crop)
    assert ingest([crop], paper_rig()).results[0].skipped == "1 board(s) found, a rig photo needs 2"
    skipped = ingest([crop], paper_rig(), min_boards=1).results[0].skipped
    assert skipped.startswith("one board alone cannot be told apart: it may be any of 'top-left', 'top-right'")
    with pytest.raises(IngestError, match="min_boards must be an integer from 1 to the rig's 4 boards, got 0"):
        ingest([crop], paper_rig(), min_boards=0)


def test_cli_render_of_a_one_board_rig_promises_no_covered_photo(rig_file, tmp_path, capsys):
    argv = ["render", "--rig", str(rig_file), "--profile", "galaxy-s8", "--n", "1", "--scale", "8"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "every 5th from the 2nd upside down)" in out and "covered" not in out


def test_split_auto_says_how_many_views_of_one_board_it_holds_out_of_k_c(rig_file, rendered, tmp_path, capsys):
    from dimenet.runtime.cli.commands.ingest import held_out_note
    from dimenet.runtime.formats.dataset import read_dataset

    folder, truth = rendered
    photos = [str(folder / str(f)) for f in truth.frame_id]
    out = tmp_path / "auto.npz"
    assert main(["ingest", *photos, "--rig", str(rig_file), "--out", str(out)]) == 0
    ds = read_dataset(out)
    test = int(ds.frames_in("test").sum())
    printed = capsys.readouterr().out
    if test:
        assert f"holds {test} of these {N_PHOTOS} views of one board out of K_c" in printed
        assert "--split train keeps them all" in printed
    else:  # the name hash put every view in train: nothing to say
        assert "holds" not in printed
    # the rule itself, on the ingested views: said under auto when some are test, never under train
    some_test = replace(ds, split=np.array(["test"] + ["train"] * (ds.n_frames - 1)))
    assert "holds 1 of these" in held_out_note("auto", some_test)
    assert held_out_note("train", some_test) == ""
