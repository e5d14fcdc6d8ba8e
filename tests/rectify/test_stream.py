"""Rectifier.stream (issue 51 step 2): one recording's K filter, its state its own, the never-worse rule on
every frame (else K_c kept), events at the start, cuts and gaps, constant memory, the gyroscope's c;
`dimenet rectify --points --temporal [--motion]`."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from dimenet.runtime import native
from dimenet.runtime.cli.main import main
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import k_matrix, k_params, solve_pnp_start
from dimenet.runtime.rectify import stream as stream_module
from dimenet.runtime.rectify.gyro_ois import CUTOFFS_HZ, GAINS, MAX_OUTSIDE_S, LensShiftOis
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.stream import FRAME_S, TAU_S, Stream
from dimenet.runtime.sim.recording import nominal_camera, simulate_recording, write_recording


@pytest.fixture(scope="module")
def recording():
    return simulate_recording(3, seconds=2.5, cuts=1)


@pytest.fixture(scope="module")
def rectifier(recording):
    camera = nominal_camera(recording)
    return Rectifier.load(K_c=camera.K, image_size=camera.image_size)


def frames(recording):
    ds = recording.dataset
    for i in range(ds.n_frames):
        m = ds.infer_mask[i]
        yield ds.points_2d[i, m], ds.points_3d[i, m], int(recording.t_ns[i])


@pytest.fixture(scope="module")
def streamed(recording, rectifier):
    stream = rectifier.stream()
    return [stream.update(*f) for f in frames(recording)]


def test_events_at_the_start_and_the_cut(recording, streamed):
    events = {i: f.event for i, f in enumerate(streamed) if f.event}
    assert events[0] == "start"
    assert recording.cuts and any(events.get(c) for c in recording.cuts)
    assert sum(1 for e in events.values() if e == "cut") <= len(recording.cuts)


def test_every_frame_is_never_worse_than_k_c(streamed):
    for f in streamed:
        r = f.result
        assert r.reprojection_error_px <= r.reprojection_error_kc_px
        if f.fused:
            sigma = np.sqrt(np.diag(r.K_cov))
            assert np.all(sigma > 0) and r.fallback is None
        else:  # K_c kept, saying why
            np.testing.assert_array_equal(r.K, r.K_c)
            assert r.fallback.refusal and r.reprojection_error_px == r.reprojection_error_kc_px


def test_the_fused_pose_is_stepped_from_the_frames_own_else_sqpnps(recording, rectifier, streamed, monkeypatch):
    """The fused K's pose: Gauss-Newton steps from the frame's own pose (not SQPnP's under the same K, and as good:
    measured, e within -0.02 to +0.024 px of SQPnP's, median -0.0005), and SQPnP's pose, with the rules again, where
    the steps find none or their pose is refused."""
    fused = [(i, f) for i, f in enumerate(streamed) if f.fused]
    assert len(fused) > 10
    points = list(frames(recording))
    stepped = 0
    for i, f in fused:
        r = f.result
        rvec, tvec = solve_pnp_start(points[i][0], points[i][1], r.K)
        e_sqpnp, _ = native.frame_error_and_depth(points[i][0], points[i][1], r.K, rvec, tvec)
        assert abs(r.reprojection_error_px - e_sqpnp) < 0.05
        stepped += not np.array_equal(np.ravel(r.rvec), np.ravel(rvec))
    assert stepped >= len(fused) // 2  # measured 41 of 58; the others' steps' pose lost to K_c, SQPnP's did not

    def no_step(*args):
        raise InputError("no step")

    monkeypatch.setattr(stream_module.native, "pose_under_k", no_step)
    stream = rectifier.stream()
    for x, X, t_ns in frames(recording):
        f = stream.update(x, X, t_ns)
        r = f.result
        assert r.reprojection_error_px <= r.reprojection_error_kc_px
        if f.fused:
            rvec, tvec = solve_pnp_start(x, X, r.K)
            np.testing.assert_array_equal(np.ravel(r.rvec), np.ravel(rvec))
            np.testing.assert_array_equal(np.ravel(r.tvec), np.ravel(tvec))


def test_the_filter_narrows_sigma_below_one_frame(streamed, rectifier):
    """Settled frames carry less uncertainty than one frame's network estimate (the evidence of many)."""
    fused = [f for f in streamed[10:] if f.fused and f.event is None and f.per_frame.K_cov is not None]
    assert fused
    one = np.median([np.sqrt(np.diag(f.per_frame.K_cov)) for f in fused], 0)
    many = np.median([np.sqrt(np.diag(f.result.K_cov)) for f in fused], 0)
    assert np.all(many < one)


def test_streams_share_one_rectifier_without_sharing_state(recording, rectifier, streamed):
    """Two streams interleaved on one Rectifier give what each gives alone (the state is the stream's)."""
    a, b = rectifier.stream(), rectifier.stream()
    out_a, out_b = [], []
    for f in list(frames(recording))[:20]:
        out_a.append(a.update(*f))
        out_b.append(b.update(*f))
    for x, y, z in zip(out_a, out_b, streamed):
        np.testing.assert_array_equal(x.result.K, z.result.K)
        np.testing.assert_array_equal(y.result.K, z.result.K)
    assert not hasattr(rectifier, "k") and not hasattr(rectifier, "P")


def test_a_gap_resets_and_memory_stays_flat(recording, rectifier):
    stream = rectifier.stream()
    fs = list(frames(recording))[:12]
    for f in fs[:6]:
        stream.update(*f)
    sizes = {k: np.asarray(v).nbytes for k, v in vars(stream).items() if isinstance(v, np.ndarray)}
    p2, p3, t = fs[6]
    assert stream.update(p2, p3, t + 2 * 10**9).event == "gap"
    for p2, p3, t in fs[7:]:
        stream.update(p2, p3, t + 2 * 10**9)
    assert sizes == {k: np.asarray(v).nbytes for k, v in vars(stream).items() if isinstance(v, np.ndarray)}


def test_ois_off_stays_within_two_sigma_of_k_c():
    """OIS off: the stream's |K - K_c| within 2 sigma on most frames (the filter does not invent motion)."""
    rec = simulate_recording(4, seconds=2.0, ois=False, cuts=0)
    camera = nominal_camera(rec)
    stream = Rectifier.load(K_c=camera.K, image_size=camera.image_size).stream()
    inside = []
    for f in frames(rec):
        out = stream.update(*f).result
        d = np.abs(k_params(out.K) - k_params(camera.K))
        inside.append(not d.any() or bool(np.all(d <= 2.0 * np.sqrt(np.diag(out.K_cov)))))
    assert np.mean(inside) >= 0.9


@pytest.mark.parametrize(
    "options", [{"tau_s": (1.0, 1.0, 0.0, 1.0)}, {"tau_s": "abcd"}, {"frame_s": float("inf")}, {"frame_s": "x"}]
)
def test_bad_options(rectifier, options):
    with pytest.raises(InputError, match="tau_s must be 4 times > 0 s and frame_s a finite time"):
        Stream(rectifier, **options)


@pytest.mark.parametrize(
    "t_ns", [float("nan"), float("inf"), 1e12 + 0.5, 2**63, -(2**63), "5", [5], True, np.uint64(2**64 - 1)]
)
def test_a_t_ns_that_is_no_integer_of_the_clock_is_refused_and_the_state_kept(recording, rectifier, streamed, t_ns):
    """t_ns is None or an integer of ns within the 64-bit clock; anything else is an InputError (not a TypeError, a
    NaN dt or a wrapped numpy subtraction) and the stream goes on as if the frame had not come."""
    stream = rectifier.stream()
    fs = list(frames(recording))[:4]
    for f in fs[:2]:
        stream.update(*f)
    with pytest.raises(InputError, match="t_ns must be None or an integer of nanoseconds"):
        stream.update(fs[2][0], fs[2][1], t_ns)
    for f, want in zip(fs[2:], streamed[2:]):
        got = stream.update(*f)
        np.testing.assert_array_equal(got.result.K, want.result.K)
        assert got.event == want.event


def test_integral_t_ns_of_any_numeric_type_is_the_int(recording, rectifier, streamed):
    stream = rectifier.stream()
    for (p2, p3, t), kind, want in zip(frames(recording), (int, np.int64, float, np.float64, np.int32), streamed):
        got = stream.update(p2, p3, kind(t - int(recording.t_ns[0])) if kind is np.int32 else kind(t))
        if kind is not np.int32:
            np.testing.assert_array_equal(got.result.K, want.result.K)
    assert stream._t_ns == int(recording.t_ns[4] - recording.t_ns[0]) and type(stream._t_ns) is int


def test_cli_temporal_writes_one_line_per_frame(recording, tmp_path, capsys):
    paths = write_recording(recording, tmp_path)
    args = ["rectify", "--points", str(paths["points"]), "--camera", str(paths["camera"]), "--temporal"]
    assert main(args) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert lines[0]["temporal"] is True
    assert len(lines) == recording.dataset.n_frames + 1
    assert lines[1]["event"] == "start" and all("fused" in line for line in lines[1:])
    assert all(line["e_px"] <= line["e_c_px"] for line in lines[1:])


def test_cli_temporal_needs_points(capsys):
    assert main(["rectify", "--example", "--temporal"]) == 2
    assert "--temporal" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "share", "loop"),
    [("motion", 0.9, {"cutoff_hz", "gain", "bias_rad_s"}), ("lens_shift", 0.5, {"gain", "scale"})],
)
def test_the_motion_predicts_c_better_than_k_c(option, share, loop):
    """With the gyroscope, c follows the OIS loop it drives; with the platform's lens-shift samples, c follows them:
    closer to the truth than K_c's centre on the settled frames (by ``share`` of its RMS error), never worse than K_c
    on the frame's points; the loop (the samples' gain) is learned."""
    rec = simulate_recording(2, seconds=5.0, cuts=0)
    camera = nominal_camera(rec)
    samples = rec.gyro if option == "motion" else rec.lens_shift
    stream = Rectifier.load(K_c=camera.K, image_size=camera.image_size).stream(**{option: samples})
    err, err_c = [], []
    for i, f in enumerate(frames(rec)):
        out = stream.update(*f)
        assert out.result.reprojection_error_px <= out.result.reprojection_error_kc_px
        if i >= 30:
            truth = k_params(rec.dataset.K_true[i])[2:]
            err.append(stream.k[2:] - truth)
            err_c.append(k_params(camera.K)[2:] - truth)
    assert np.sqrt(np.mean(np.square(err))) < share * np.sqrt(np.mean(np.square(err_c)))
    assert set(stream.gyro.loop()) == loop and stream.gyro.loop()["gain"] > 0


def test_the_lens_shift_is_interpolated_and_scaled(rectifier):
    ois = LensShiftOis(np.array([[0, 0.0, 10.0], [100, 10.0, -10.0]]), np.array([3000.0, 3000.0, 2000.0, 1500.0]), 0.5)
    ois.advance(25)
    np.testing.assert_allclose(ois._shifts(), [[1.25, 2.5]])
    ois.advance(1000)  # after the last sample: the last
    np.testing.assert_allclose(ois._shifts(), [[5.0, -5.0]])
    for bad in (0.0, -1.0, float("nan"), 1e300, "x", None):
        with pytest.raises(InputError, match="scale"):
            LensShiftOis(np.array([[0, 0.0, 0.0], [1, 0.0, 0.0]]), np.zeros(4), bad)
    for bad in (np.nan, 1e300):
        with pytest.raises(InputError, match="finite, within"):
            LensShiftOis(np.array([[0, 0.0, bad], [1, 0.0, 0.0]]), np.zeros(4))
    with pytest.raises(InputError, match="finite, within"):  # deg/s for rad/s
        rectifier.stream(motion=np.array([[0, 0.0, 0.0, 0.0], [1, 500.0, 0.0, 0.0]]))
    with pytest.raises(InputError, match="t_ns increasing"):
        LensShiftOis(np.array([[0, 0.0, 0.0], [np.nan, 0.0, 0.0]]), np.zeros(4))
    with pytest.raises(InputError, match="not both"):
        rectifier.stream(motion=np.zeros((2, 4)), lens_shift=np.zeros((2, 3)))


def test_the_loop_bank_scores_its_pairs_at_poses_stepped_from_the_frames(recording, rectifier, monkeypatch):
    """The OIS loop bank scores each (cutoff, gain) pair's K at a pose stepped from the frame's own (one
    ``native.pose_under_k`` per pair), not at a fresh SQPnP: a scoring frame calls the steps once per pair that moves
    c, plus the tracked f's; SQPnP runs only where the steps find no pose."""
    calls, sqpnp = [], []
    steps, error_at_pnp = native.pose_under_k, native.error_at_pnp
    monkeypatch.setattr(native, "pose_under_k", lambda *a, **k: calls.append(1) or steps(*a, **k))
    monkeypatch.setattr(native, "error_at_pnp", lambda *a: sqpnp.append(1) or error_at_pnp(*a))
    stream = rectifier.stream(motion=recording.gyro)
    x, X, t_ns = next(frames(recording))
    before = len(calls)
    stream.update(x, X, t_ns)  # the first frame scores the bank
    moving = len(CUTOFFS_HZ) * sum(1 for g in GAINS if g) + 1  # the no-OIS pair once, then the tracked f
    assert len(calls) - before >= moving + 1 and not sqpnp


def test_motion_needs_t_ns(recording, rectifier):
    stream = rectifier.stream(motion=recording.gyro)
    p2, p3, _ = next(frames(recording))
    with pytest.raises(InputError, match="t_ns"):
        stream.update(p2, p3, None)


def test_cli_motion(recording, tmp_path, capsys):
    paths = write_recording(recording, tmp_path)
    args = ["rectify", "--points", str(paths["points"]), "--camera", str(paths["camera"])]
    assert main([*args, "--temporal", "--motion", str(paths["gyro"])]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert lines[0]["motion"] == str(paths["gyro"]) and len(lines) == recording.dataset.n_frames + 1
    assert main([*args, "--motion", str(paths["gyro"])]) == 2
    assert "--temporal" in capsys.readouterr().err
    assert main([*args, "--temporal", "--motion", str(paths["ois"]), "--ois-scale", "1"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert lines[0]["motion"] == str(paths["ois"]) and len(lines) == recording.dataset.n_frames + 1
    for extra, why in (
        (["--motion", str(paths["gyro"]), "--ois-scale", "0.5"], "gyroscope"),
        (["--ois-scale", "0.5"], "--motion"),
        (["--motion", str(paths["ois"]), "--ois-scale", "0"], "--ois-scale"),
        (["--motion", str(paths["ois"]), "--ois-scale", "1e300"], "--ois-scale"),
    ):
        assert main([*args, "--temporal", *extra]) == 2
        err = capsys.readouterr().err
        assert why in err and err.count("\n") == 1, err


def test_a_stream_given_the_rectifiers_own_k_c_on_every_frame_is_the_plain_stream(recording, rectifier, streamed):
    stream = rectifier.stream()
    for f, plain in zip(frames(recording), streamed):
        out = stream.update(*f, K_c=rectifier.K_c)
        np.testing.assert_array_equal(out.result.K, plain.result.K)
        np.testing.assert_array_equal(out.result.K_cov, plain.result.K_cov)
        assert (out.event, out.fused) == (plain.event, plain.fused)
        assert out.result.fallback_code == plain.result.fallback_code


def test_a_stream_about_each_frames_own_k_c(recording, rectifier, without_evidence_rule):
    """The platform's per-frame K as each frame's K_c: e_c, the never-worse rule and a refused frame are under the
    frame's own K_c, and Delta K is from it (the evidence rule off: on these natural labels it keeps the frame's
    K_c as the evidence of most frames, and the fused K would stand on few)."""
    K_platform = recording.dataset.K_platform
    stream, fused = rectifier.stream(), 0
    for i, f in enumerate(frames(recording)):
        out = stream.update(*f, K_c=K_platform[i])
        r = out.result
        np.testing.assert_array_equal(r.K_c, K_platform[i])
        assert r.reprojection_error_px <= r.reprojection_error_kc_px
        np.testing.assert_allclose(r.delta_k, k_params(r.K) - k_params(K_platform[i]), atol=1e-9)
        if out.fused:
            fused += 1
        else:
            np.testing.assert_array_equal(r.K, K_platform[i])
            assert r.fallback.refusal
    assert fused > len(K_platform) // 2


class _Evidence:
    """A Rectifier whose frames say K = K_c + offset_px with covariance cov_px2 (the real result otherwise)."""

    def __init__(self, rectifier, offset_px, cov_px2):
        self._rectifier, self.offset_px, self.cov_px2 = rectifier, offset_px, cov_px2

    def __getattr__(self, name):
        return getattr(self._rectifier, name)

    def rectify(self, points_2d, points_3d, *, refine=False, K_c=None):
        res = self._rectifier.rectify(points_2d, points_3d, refine=refine, K_c=K_c)
        cov = self.cov_px2
        return replace(res, K=k_matrix(k_params(res.K_c) + self.offset_px), covariance=lambda: cov)


def test_the_state_is_the_offset_from_each_frames_k_c(recording, rectifier):
    """A K_c moving 4 px a frame with weak evidence after the first: the state keeps its offset from each frame's
    K_c (drawn back by the AR(1)), where a state about one K_c would lag the moving K_c by tens of px."""
    offset = np.array([6.0, 6.0, -9.0, 5.0])
    evidence = _Evidence(rectifier, offset, np.eye(4) * 1e-6)
    stream = Stream(evidence)
    K = rectifier.K_c.copy()
    for i, (p2, p3, _) in enumerate(list(frames(recording))[:20]):
        K[0, 2], K[1, 2] = rectifier.K_c[0, 2] + 4.0 * i, rectifier.K_c[1, 2] - 4.0 * i
        stream.update(p2, p3, None, K_c=K)
        evidence.cov_px2 = np.eye(4) * 1e12  # after the first frame the frames say almost nothing
    a = np.exp(-FRAME_S / np.asarray(TAU_S)) ** 19
    np.testing.assert_allclose(stream.k - k_params(K), a * offset, atol=0.05)


def test_a_frame_the_stream_refuses_under_its_own_k_c_reports_that_camera_s_population_spread(
    recording, rectifier, monkeypatch, without_evidence_rule
):
    """Where the stream's K is refused under a frame's own K_c, the frame keeps that K_c with the K_cov a refused
    ``rectify`` under it reports (``Rectifier.frame_population_K_cov``), not the Rectifier's camera's."""
    monkeypatch.setattr(stream_module, "loses_to_k_c", lambda e, e_c, f: True)  # the stream's K always fits worse
    p2, p3, t = next(frames(recording))
    K = recording.dataset.K_platform[0]  # the platform's K: f about 1 % off the Rectifier's
    out = rectifier.stream().update(p2, p3, t, K_c=K)
    assert not out.fused and out.result.fallback.refusal and out.per_frame.fallback is None
    np.testing.assert_array_equal(out.result.K, K)
    want = rectifier.frame_population_K_cov(K)
    np.testing.assert_array_equal(out.result.K_cov, want)
    assert not np.allclose(want, rectifier.population_K_cov)  # a camera of other focal length: other pixels
    np.testing.assert_array_equal(rectifier.frame_population_K_cov(), rectifier.population_K_cov)


def test_the_gyroscope_s_bias_and_high_pass_follow_their_recursions_to_the_bit():
    """GyroOis.advance (Python floats) against the recursions written in numpy arrays: the bias's running mean
    b += min(1, dt / min(t, BIAS_TAU_S)) (g - b), then per cutoff hp = a (hp + (g - b) dt) with a = 1 / (1 + 2 pi f dt),
    yaw from the rate about y, pitch about x; a recentre zeroes hp only."""
    from dimenet.runtime.rectify.gyro_ois import BIAS_TAU_S, GyroOis

    rng = np.random.default_rng(2)
    t = np.cumsum(rng.integers(2_000_000, 8_000_000, 400)) + 10**12  # ns
    samples = np.c_[t, rng.normal(0.02, 0.3, (400, 3))]
    gyro = GyroOis(samples, np.array([3000.0, 3000.0, 2000.0, 1500.0]))
    bias, bias_s, hp = np.zeros(3), 0.0, np.zeros((len(CUTOFFS_HZ), 2))
    cutoffs = np.asarray(CUTOFFS_HZ)
    for i in range(1, len(samples)):
        step_s = (samples[i, 0] - samples[i - 1, 0]) * 1e-9
        bias_s += step_s
        bias = bias + min(1.0, step_s / min(bias_s, BIAS_TAU_S)) * (samples[i, 1:] - bias)
        rate = samples[i, 1:] - bias
        hp = (1.0 / (1.0 + 2.0 * np.pi * cutoffs * step_s))[:, None] * (hp + np.array([rate[1], rate[0]]) * step_s)
        if i == 200:
            gyro.advance(int(samples[i, 0]))
            hp[:] = 0.0
            gyro.recentre()
    gyro.advance(int(samples[-1, 0]))
    np.testing.assert_array_equal(gyro.loop()["bias_rad_s"], bias)
    np.testing.assert_array_equal(gyro._shifts(), 3000.0 * np.stack([np.tan(hp[:, 0]), -np.tan(hp[:, 1])], 1))


@pytest.mark.parametrize("option", ["motion", "lens_shift"])
def test_a_frame_outside_the_motion_s_samples_is_refused_as_on_another_clock(recording, rectifier, option):
    """Samples on another clock than the points' (here 11.6 days later) would leave c at K_c's (the gyroscope) or at
    the first sample's shift (the lens shift) without a word: a frame more than MAX_OUTSIDE_S outside their span is
    an InputError naming both, and the stream is as it was; within it, the frame is taken."""
    samples = getattr(recording, "gyro" if option == "motion" else "lens_shift")
    later = np.c_[samples[:, 0] + 10.0**15, samples[:, 1:]]
    fs = list(frames(recording))
    stream = rectifier.stream(**{option: later})
    with pytest.raises(InputError, match=r"outside the motion's samples .*on the points' clock"):
        stream.update(*fs[0])
    assert stream.k is None  # nothing of the frame was taken
    first = int(later[0, 0])
    p2, p3, _ = fs[0]
    assert stream.update(p2, p3, first - int(MAX_OUTSIDE_S * 1e9) + 1000).event == "start"  # 1 us inside the edge


def test_a_stream_with_motion_refuses_a_frames_own_k_c(recording, rectifier):
    stream = rectifier.stream(motion=recording.gyro)
    p2, p3, t = next(frames(recording))
    with pytest.raises(InputError, match="one K_c"):
        stream.update(p2, p3, t, K_c=recording.dataset.K_platform[0])
