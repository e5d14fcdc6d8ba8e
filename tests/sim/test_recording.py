"""Recordings (issue 51 step 1): time, the OIS loop, the gyroscope and the files a recording writes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dimenet.runtime.errors import InputError, PointsError
from dimenet.runtime.evaluation.metrics import reprojection_error_under_k
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.motion import GYRO, LENS_SHIFT, read_motion, write_gyro, write_lens_shift
from dimenet.runtime.formats.points import read_points
from dimenet.runtime.geometry import k_params
from dimenet.runtime.sim.recording import TRACE_RANGES, draw_trace, simulate_recording, write_recording


@pytest.fixture(scope="module")
def recording():
    return simulate_recording(1, seconds=3.0, cuts=1)


def test_deterministic_and_timed(recording):
    again = simulate_recording(1, seconds=3.0, cuts=1)
    np.testing.assert_array_equal(again.dataset.points_2d, recording.dataset.points_2d)
    fps = recording.dataset.meta["recording"]["trace"]["fps"]
    steps = np.diff(recording.t_ns)
    assert np.all(steps > 0)
    assert np.median(steps) == pytest.approx(1e9 / fps, abs=1)


def test_truth_fits_the_held_out_points(recording):
    """Under K_true the held-out points fit to their corner noise; under K_c (the nominal K) they fit worse."""
    ds = recording.dataset
    held = ds.valid & ~ds.infer_mask
    assert held.sum(1).min() > 0 and np.all((ds.infer_mask & held) == 0)
    e_true = reprojection_error_under_k(ds.points_2d, ds.points_3d, held, ds.K_true)
    assert e_true.mean() < 2.0 * ds.meta["device"]["corner_sigma_px"]


def test_ois_moves_c_and_off_keeps_it(recording):
    c = k_params(recording.dataset.K_true)[:, 2:]
    assert c.std(0).min() > 1.0  # px: the lens moves
    off = simulate_recording(1, seconds=3.0, ois=False)
    c_off = k_params(off.dataset.K_true)[:, 2:]
    np.testing.assert_allclose(c_off, np.broadcast_to(c_off[0], c_off.shape), atol=1e-9)


def test_cut_moves_the_pose_and_refocus_steps_f(recording):
    assert len(recording.cuts) == 1
    cut = recording.cuts[0]
    f = recording.dataset.K_true[:, 0, 0]
    steps = np.flatnonzero(np.diff(f) != 0) + 1
    assert set(steps) <= set(recording.refocus) and cut in recording.refocus


def test_gyro_measures_the_rotation_that_moves_c():
    """The OIS shift follows the rotation the gyroscope measures: with OIS on, cx moves with the integrated yaw
    rate's high-pass, so cx and the integrated gy correlate positively (cx = +f tan(hp yaw))."""
    rec = simulate_recording(2, seconds=4.0, cuts=0)
    trace = rec.dataset.meta["recording"]["trace"]
    g = rec.gyro
    dt = np.diff(g[:, 0]) * 1e-9
    yaw = np.r_[0.0, np.cumsum((g[1:, 2] - trace["gyro_bias_rad_s"][1]) * dt)]
    at = np.searchsorted(g[:, 0], rec.t_ns)
    cx = rec.dataset.K_true[:, 0, 2]
    hp = yaw[at] - np.convolve(yaw[at], np.ones(15) / 15, "same")
    assert np.corrcoef(hp[10:-10], cx[10:-10] - cx.mean())[0, 1] > 0.5


def test_held_out_traces_draw_from_their_own_ranges():
    rng = np.random.default_rng(0)
    for _ in range(20):
        t = draw_trace(rng, held_out=True)
        low, high = TRACE_RANGES["ois_cutoff_hz"][1]
        assert low <= t.ois_cutoff_hz <= high and t.held_out
        assert low <= t.ois_cutoff_hz and math.isfinite(np.linalg.norm(t.gyro_bias_rad_s))


def test_files_round_trip(recording, tmp_path):
    paths = write_recording(recording, tmp_path)
    frames = list(read_points(paths["points"]))
    ds = recording.dataset
    assert len(frames) == ds.n_frames
    assert [f.t_ns for f in frames] == recording.t_ns.tolist()
    np.testing.assert_array_equal(frames[3].points_2d, ds.points_2d[3, ds.infer_mask[3]])
    assert all(f.K_c is None for f in frames)
    platform = list(read_points(paths["points_platform"]))  # format 2: the same points, the platform's K per frame
    assert [f.t_ns for f in platform] == recording.t_ns.tolist()
    np.testing.assert_array_equal(platform[3].points_3d, frames[3].points_3d)
    np.testing.assert_array_equal(np.stack([f.K_c for f in platform]), ds.K_platform)
    gyro, ois = read_motion(paths["gyro"]), read_motion(paths["ois"])
    assert gyro.kind == GYRO and ois.kind == LENS_SHIFT
    np.testing.assert_array_equal(gyro.samples, recording.gyro)
    np.testing.assert_array_equal(ois.samples, recording.lens_shift)
    np.testing.assert_array_equal(read_dataset(paths["truth"]).K_true, ds.K_true)


def test_motion_file_errors_name_the_line(tmp_path):
    path = tmp_path / "g.csv"
    write_gyro(path, np.array([[10, 0.1, 0.2, 0.3], [20, 0.1, 0.2, 0.3]]))
    path.write_text(path.read_text() + "15,0,0,0\n")
    with pytest.raises(PointsError, match=r"g.csv:4: t_ns must increase"):
        read_motion(path)
    path.write_text("t_ns,gx_rad_s,gy_rad_s,gz_rad_s\n1,0,0,300\n2,0,0,0\n")
    with pytest.raises(PointsError, match=r":2: .*deg/s"):
        read_motion(path)
    write_lens_shift(path, np.array([[10, 1.5, -2.0], [20, 1.0, 0.5]]))
    path.write_text(path.read_text() + "30,nan,0\n")
    with pytest.raises(PointsError, match=r"g.csv:4: x_shift_px, y_shift_px must be finite px"):
        read_motion(path)
    path.write_text("t_ns,x_shift_px,y_shift_px\n10,1,2\n")
    with pytest.raises(PointsError, match=r"at least 2 samples"):
        read_motion(path)
    path.write_text("t_ns,x_shift_px,y_shift_px\n10,1,2\n20,1,\x002\n")  # csv refuses NUL before Python 3.11
    with pytest.raises(PointsError, match=r"g.csv(:3: x_shift_px, y_shift_px must be finite px|: not a readable CSV)"):
        read_motion(path)
    path.write_text("t_ns,x_px,y_px\n10,1,2\n")
    with pytest.raises(PointsError, match=r"g.csv:1: the header must name .*gx_rad_s.* or .*x_shift_px"):
        read_motion(path)


@pytest.mark.parametrize(
    "t_ns, message",
    [
        ("1" * 400, "must be an integer"),  # float() of it overflowed
        ("1" * 5000, "must be an integer"),  # int() refuses more than 4300 digits
        ("\u00b2", "must be an integer"),  # str.isdigit() takes a superscript two, int() does not
        ("\u0661\u0662", "must be an integer"),  # Arabic-Indic digits: int() reads 12
        (str(2**63), "must be an integer"),  # past the 64-bit clock
        ("1.5", "must be an integer"),
        ("9000000000000000001", "one float64 at this magnitude"),  # 1 ns after the first sample: no float64 between
    ],
)
def test_a_motion_file_s_t_ns_is_an_integer_of_the_64_bit_clock(tmp_path, t_ns, message):
    """The motion reader takes t_ns by the points reader's rule (``formats.text.t_ns_integer``)."""
    path = tmp_path / "g.csv"
    path.write_text(f"t_ns,gx_rad_s,gy_rad_s,gz_rad_s\n9000000000000000000,0,0,0\n{t_ns},0,0,0\n", encoding="utf-8")
    with pytest.raises(PointsError, match=rf"g.csv:3: t_ns .*{message}"):
        read_motion(path)
    path.write_text("t_ns,gx_rad_s,gy_rad_s,gz_rad_s\n-9000000000000000000,0,0,0\n+0042,0,0,0\n", encoding="utf-8")
    np.testing.assert_array_equal(read_motion(path).samples[:, 0], [-9e18, 42.0])


def test_the_lens_shift_samples_follow_the_true_principal_point(recording):
    """The platform's lens-shift samples, interpolated at each frame's time, against K_true's c - the nominal
    centre: the same motion up to the samples' gain and noise (and focus breathing's share of f)."""
    ds = recording.dataset
    samples = recording.lens_shift
    shift = np.stack([np.interp(recording.t_ns, samples[:, 0], samples[:, a]) for a in (1, 2)], 1)
    truth = ds.K_true[:, :2, 2] - ds.K_true[0, :2, 2] + shift[0]
    assert np.corrcoef(shift[:, 0], truth[:, 0])[0, 1] > 0.9 and np.corrcoef(shift[:, 1], truth[:, 1])[0, 1] > 0.9


def test_bad_arguments():
    with pytest.raises(InputError, match="kind"):
        simulate_recording(0, kind="video")
    with pytest.raises(InputError, match="seconds"):
        simulate_recording(0, seconds=0)


def test_platform_k_as_users_report_it(recording):
    """K_platform: f off by the drawn bias, c following the true shift with the gain one frame late, quantised."""
    ds = recording.dataset
    sdk = ds.meta["platform_k"]
    assert sdk["model"] == "reported/1" and 0.005 <= abs(sdk["f_bias_rel"]) <= 0.02 and 0.7 <= sdk["c_gain"] <= 1.0
    f_true, f_sdk = ds.K_true[:, 0, 0], ds.K_platform[:, 0, 0]
    np.testing.assert_allclose(f_sdk, f_true * (1 + sdk["f_bias_rel"]), atol=0.25)
    rest = np.array(ds.meta["device"]["centre_offset_px"]) + (np.array(ds.meta["device"]["image_size_px"]) - 1) / 2
    expected = rest + sdk["c_gain"] * (ds.K_true[:-1, :2, 2] - rest)
    np.testing.assert_allclose(ds.K_platform[1:, :2, 2], expected, atol=0.25)
    np.testing.assert_array_equal(ds.K_platform[:, :2, :] * 2, np.round(ds.K_platform[:, :2, :] * 2))
