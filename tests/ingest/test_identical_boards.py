"""A four-board rig of identical boards (same pattern and size) on the two faces of a fold, rendered at 1/3
of 12 MP: every photo that shows all four boards whole gives a frame of four boards, each the right one.

Before, the first two boards found could lie in one plane (no K: "the points found lie in one plane") or
fit two labellings alike, whose winner's camera put the others where they are not ("ambiguous board
identity", 2 boards found of 4): 5 of these 8 photos were skipped. A photo that shows only two boards
whole, one on each face, is told apart by nothing but their small offsets: it may still be refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dimenet.runtime.bench.ingest_score import score
from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import load_rig
from dimenet.runtime.ingest.pipeline import ingest
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, scaled_profile, write_render


def _board(name: str, turn_rad: float, origin_mm: list) -> dict:
    return {"name": name, "inner_corners": [9, 6], "square_mm": 30.0, "rvec": [0.0, turn_rad, 0.0],
            "tvec_mm": origin_mm, "aruco": None}  # fmt: skip


FOLD = {
    "format": "dimenet-rig/1",
    "units": "mm",
    "boards": [
        _board("left-top", -0.698132, [-229.813, -210.0, -192.836]),
        _board("left-bottom", -0.698132, [-252.795, 40.0, -212.12]),
        _board("right-top", 0.523599, [51.962, -150.0, -30.0]),
        _board("right-bottom", 0.523599, [64.952, 95.0, -37.5]),
    ],
}


@pytest.fixture(scope="module")
def fold(tmp_path_factory):
    root = tmp_path_factory.mktemp("fold")
    (root / "rig.json").write_text(json.dumps(FOLD))
    rig = load_rig(root / "rig.json")
    write_render(root / "shots", rig, scaled_profile(get_profile("galaxy-s8"), 3.0), 8, seed=2)
    truth = read_truth(root / "shots" / TRUTH_FILE)
    result = ingest([root / "shots" / str(f) for f in truth.frame_id], rig, split="train")
    return rig, truth, result


def test_every_photo_of_all_four_boards_gives_all_four_right(fold):
    rig, truth, result = fold
    whole = np.array([[truth.seen[i][truth.board_of_point == b].all() for b in range(4)] for i in range(8)])
    assert whole.all(1).sum() >= 4  # the case is exercised
    by_name = {p.name: p for p in result.results}
    for i in np.flatnonzero(whole.all(1)):
        photo = by_name[str(truth.frame_id[i])]
        assert photo.skipped is None and photo.boards == (0, 1, 2, 3), (photo.name, photo.skipped)
    s = score(result.dataset, truth)
    assert s.identity_errors == 0 and s.corner_rms_px < 0.5
