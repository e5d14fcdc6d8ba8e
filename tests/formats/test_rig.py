import copy
import json

import numpy as np
import pytest

from dimenet.runtime.errors import RigError
from dimenet.runtime.formats.rig import Board, load_rig, paper_rig, rig_from_dict, rig_to_dict
from dimenet.runtime.sim.scene_geometry import board_surface


def test_paper_rig_is_four_10x8_boards_of_22mm():
    rig = paper_rig()
    assert len(rig.boards) == 4
    assert all(b.inner_corners == (10, 8) and b.square_mm == 22.0 and b.aruco is None for b in rig.boards)
    assert rig.points().shape == (320, 3) and rig.n_points == 320
    np.testing.assert_array_equal(rig.board_of_point, np.repeat(np.arange(4), 80))
    for k, board in enumerate(rig.boards):
        np.testing.assert_allclose(rig.points()[rig.board_of_point == k], board.points())


def test_paper_rig_is_non_planar_with_four_distinct_planes():
    rig = paper_rig()
    points = rig.points()
    sv = np.linalg.svd(points - points.mean(0), compute_uv=False)
    assert sv[2] > 0.15 * sv[0]  # far from one plane: K is observable from one view
    normals = np.array([b.normal() for b in rig.boards])
    angles = np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1)))
    assert angles[~np.eye(4, dtype=bool)].min() > 20  # four different planes
    for board in rig.boards:  # each board's corners lie on its own plane
        np.testing.assert_allclose((board.points() - board.tvec_mm) @ board.normal(), 0, atol=1e-9)


def _footprint(board):
    corner, a, b = board_surface(board)
    return np.array([corner, corner + a, corner + a + b, corner + b])[:, :2]


def _separated(p, q):
    """Separating-axis test for two convex polygons (vertex arrays in order)."""
    for poly in (p, q):
        for e in np.diff(np.vstack([poly, poly[:1]]), axis=0):
            axis = np.array([-e[1], e[0]])
            if (p @ axis).max() < (q @ axis).min() or (q @ axis).max() < (p @ axis).min():
                return True
    return False


def test_paper_rig_boards_do_not_overlap_and_fit_half_a_metre():
    rig = paper_rig()
    feet = [_footprint(b) for b in rig.boards]
    for i in range(4):
        for j in range(i + 1, 4):
            assert _separated(feet[i], feet[j]), (rig.boards[i].name, rig.boards[j].name)
    extent = np.ptp(np.vstack(feet), axis=0)
    assert extent.max() <= 500.0  # printed patterns, mm, seen along the rig normal


def test_corners_are_ordered_row_by_row_i_inner_j_outer():
    board = Board(name="b", inner_corners=(3, 2), square_mm=10.0, rvec=(0.0, 0.0, 0.0), tvec_mm=(1.0, 2.0, 3.0))
    expected = [(0, 0), (10, 0), (20, 0), (0, 10), (10, 10), (20, 10)]
    np.testing.assert_allclose(board.local_points()[:, :2], expected)
    np.testing.assert_allclose(board.points(), board.local_points() + [1.0, 2.0, 3.0])


def test_board_pose_rotates_then_translates():
    board = Board(name="b", inner_corners=(2, 2), square_mm=10.0, rvec=(0.0, 0.0, np.pi / 2), tvec_mm=(5.0, 0.0, 0.0))
    # (10, 0, 0) turned 90 degrees about z is (0, 10, 0); then shifted by 5 mm along x.
    np.testing.assert_allclose(board.points()[1], [5.0, 10.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(board.normal(), [0.0, 0.0, 1.0], atol=1e-12)


def test_corners_are_computed_once_and_shared_read_only():
    rig = paper_rig()
    for points in (rig.points(), rig.boards[0].points(), rig.boards[0].rotation()):
        assert not points.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            points[0] = 0.0
    assert rig.points() is rig.points() and rig.boards[0].points() is rig.boards[0].points()
    np.testing.assert_array_equal(rig.points()[: rig.boards[0].n_points], rig.boards[0].points())


def test_round_trip_dict_and_json_file(tmp_path):
    rig = paper_rig()
    d = rig_to_dict(rig)
    assert rig_from_dict(d) == rig
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(d))
    assert load_rig(path) == rig
    with_aruco = copy.deepcopy(d)
    with_aruco["boards"][0]["aruco"] = {"dictionary": "DICT_4X4_50", "first_id": 0, "marker_mm": 16.0}
    back = rig_from_dict(json.loads(json.dumps(with_aruco)))
    assert back.boards[0].aruco.marker_mm == 16.0 and rig_to_dict(back) == with_aruco


def _mutated(path, value):
    d = rig_to_dict(paper_rig())
    target = d
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return d


@pytest.mark.parametrize(
    "path, value, field",
    [
        (("format",), "dimenet-rig/2", "format"),
        (("units",), "cm", "units"),
        (("boards",), [], "boards"),
        (("boards", 1, "inner_corners"), [1, 8], "boards[1].inner_corners"),
        (("boards", 1, "inner_corners"), [10.5, 8], "boards[1].inner_corners"),
        (("boards", 2, "square_mm"), -22.0, "boards[2].square_mm"),
        (("boards", 2, "square_mm"), "22", "boards[2].square_mm"),
        (("boards", 0, "rvec"), [0.0, 0.1], "boards[0].rvec"),
        (("boards", 0, "tvec_mm"), [0.0, float("nan"), 0.0], "boards[0].tvec_mm[1]"),
        (("boards", 3, "name"), "top-left", "boards[3].name"),
        (("boards", 3, "name"), "", "boards[3].name"),
        (("boards", 0, "square"), 22.0, "boards[0].square"),
        (("boards", 0, "tvec_mm"), KeyError, "boards[0].tvec_mm"),
        (
            ("boards", 0, "aruco"),
            {"dictionary": "DICT_NOPE", "first_id": 0, "marker_mm": 16.0},
            "boards[0].aruco.dictionary",
        ),
        (
            ("boards", 0, "aruco"),
            {"dictionary": "DICT_4X4_50", "first_id": -1, "marker_mm": 16.0},
            "boards[0].aruco.first_id",
        ),
        (
            ("boards", 0, "aruco"),
            {"dictionary": "DICT_4X4_50", "first_id": 0, "marker_mm": 30.0},
            "boards[0].aruco.marker_mm",
        ),
        (("extra",), 1, "extra"),
    ],
)
def test_bad_specs_raise_rig_error_naming_the_field(path, value, field):
    with pytest.raises(RigError) as exc:
        rig_from_dict(_mutated(path, value))
    assert str(exc.value).startswith(f"{field}: ")


def test_load_rig_reports_unreadable_and_invalid_files(tmp_path):
    with pytest.raises(RigError, match="cannot read"):
        load_rig(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(RigError, match="not valid JSON"):
        load_rig(bad)
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps(_mutated(("units",), "inch")))
    with pytest.raises(RigError, match=r"wrong\.json: units"):
        load_rig(wrong)
