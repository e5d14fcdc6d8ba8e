"""The compiled core's pose kernel (``dimenet_pose_steps``) against the numpy reference, to the bit: with no
step, the check stage's e(K) and depth (``native.frame_error_and_depth``, ``geometry.frame_error_and_depth``);
with steps, the Gauss-Newton pose under a K from the C0 pose (``geometry.pose_step``, stage pnp_k's), and that pose
against SQPnP's under K on the bench's frames under each model's own K (BENCHMARKS.md, "The pose under K")."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import native
from dimenet.runtime.bench.latency import bench_frames, bench_rectifier
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import frame_error_and_depth, k_matrix, k_params
from dimenet.runtime.geometry import solve_pnp_start as pnp
from dimenet.runtime.geometry.pose_step import POSE_STEPS, pose_steps, pose_under_k
from dimenet.runtime.rectify import stages
from dimenet.runtime.rectify.checks import validated_frame
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier

needs_core = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")

GOLDEN_DIR = Path(__file__).resolve().parents[2] / "models_spec" / "golden"
GOLDEN = {"default": GOLDEN_DIR / "golden.json", "paper-rig": GOLDEN_DIR / "paper-rig" / "golden.json"}
BENCH_FRAMES = 2000


def both(*args, steps=POSE_STEPS):
    """native.pose_under_k (rvec, tvec, e, depth) under numpy, then under the compiled core."""
    out = []
    for name in ("python", "c"):
        with native.using(name):
            out.append(native.pose_under_k(*args, steps))
    return out


def frame_k(rect: Rectifier, p2, p3):
    """One frame's model-px points, the network's k (4,) px and the C0 pose (as ``rectify`` reaches pnp_k)."""
    cam = rect._cam
    _, q2, q3, _ = validated_frame(cam.image, cam.to_model, p2, p3)
    r0, t0 = pnp(q2, q3, cam.K_c)
    feats, _ = stages.frame_features(cam, q2, q3, r0, t0)
    return q2, q3, cam.k_c + rect.model.frame_delta_k(feats), r0, t0


@pytest.fixture(scope="module")
def bench_set():
    rectifiers = {name: bench_rectifier(load_model(name), "dimenet") for name in sorted(GOLDEN)}
    p2, p3 = bench_frames(BENCH_FRAMES, 320, rectifiers["default"].image_size)
    return rectifiers, p2, p3


@needs_core
@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_the_core_gives_the_references_pose_to_the_bit_on_2000_bench_frames(bench_set, name):
    rectifiers, p2, p3 = bench_set
    for b in range(BENCH_FRAMES):
        args = frame_k(rectifiers[name], p2[b], p3[b])
        (r_py, t_py, e_py, z_py), (r_c, t_c, e_c, z_c) = both(*args)
        assert np.array_equal(r_py, r_c) and np.array_equal(t_py, t_c) and (e_py, z_py) == (e_c, z_c), b


@needs_core
@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_the_core_gives_the_references_pose_on_the_golden_frames(name):
    for frame in json.loads(GOLDEN[name].read_text())["frames"]:
        x = frame["inputs"]
        rect = Rectifier.load(name, K_c=np.array(x["K_c"]), image_size=tuple(int(v) for v in x["image_size"]))
        try:
            args = frame_k(rect, np.array(x["points_2d"]), np.array(x["points_3d"]))
        except InputError:
            continue  # a frame the input rules refuse
        for steps in (0, 1, POSE_STEPS, 5):
            (r_py, t_py, e_py, z_py), (r_c, t_c, e_c, z_c) = both(*args, steps=steps)
            assert np.array_equal(r_py, r_c) and np.array_equal(t_py, t_c), (frame["name"], steps)
            assert (e_py, z_py) == (e_c, z_c), (frame["name"], steps)


@needs_core
def test_both_refuse_the_same_frames_with_the_same_message():
    rng = np.random.default_rng(7)
    x, X, _, rvec, tvec = random_frames(rng, frames=1, points=40)
    k = k_params(K_TEST)
    same_point = np.repeat(x[0, :1], 40, axis=0), np.repeat(X[0, :1], 40, axis=0)
    nan_pixel = x[0].copy()
    nan_pixel[3, 0] = np.nan
    for p2, p3 in (same_point, (nan_pixel, X[0])):
        messages = []
        for name in ("python", "c"):
            with native.using(name), pytest.raises(InputError) as info:
                native.pose_under_k(p2, p3, k, rvec[0], tvec[0])
            messages.append(str(info.value))
        assert messages[0] == messages[1] == "no Gauss-Newton step: the points fix no pose under K"


def test_other_layouts_are_taken_as_numpy_takes_them():
    rng = np.random.default_rng(8)
    x, X, _, rvec, tvec = random_frames(rng, frames=1, points=30)
    k = k_params(K_TEST) + 2.0
    want = pose_under_k(x[0], X[0], k, rvec[0], tvec[0])
    got = native.pose_under_k(np.asfortranarray(x[0]), np.asfortranarray(X[0]), list(k), rvec[0], tvec[0])
    assert np.array_equal(want[0], got[0]) and np.array_equal(want[1], got[1]) and want[2:] == got[2:]


def test_the_steps_reach_the_least_squares_pose_and_stay_near_sqpnps(bench_set):
    """On 200 bench frames under each model's K: e after POSE_STEPS steps within 1e-4 px of the converged
    least-squares pose's, and within 0.02 px of SQPnP's under K (lower on most frames: the steps minimise
    the reprojection error, SQPnP an object-space error); the worse rule decides the same."""
    rectifiers, p2, p3 = bench_set
    for name, rect in rectifiers.items():
        lower = 0
        for b in range(200):
            q2, q3, k, r0, t0 = frame_k(rect, p2[b], p3[b])
            K = k_matrix(k)
            e_steps = native.pose_under_k(q2, q3, k, r0, t0)[2]
            e_converged = frame_error_and_depth(q2, q3, K, *pose_steps(q2, q3, k, r0, t0, 8))[0]
            e_sqpnp = frame_error_and_depth(q2, q3, K, *pnp(q2, q3, K))[0]
            e_c = frame_error_and_depth(q2, q3, rect._cam.K_c, r0, t0)[0]
            assert abs(e_steps - e_converged) <= 1e-4 and abs(e_steps - e_sqpnp) <= 0.02, (name, b)
            assert (e_steps > e_c) == (e_sqpnp > e_c), (name, b)
            lower += e_steps <= e_sqpnp
        assert lower >= 120, (name, lower)


@needs_core
@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_the_check_stages_error_and_depth_are_the_references_to_the_bit(bench_set, name):
    rectifiers, p2, p3 = bench_set
    for b in range(0, BENCH_FRAMES, 4):
        q2, q3, k, r0, t0 = frame_k(rectifiers[name], p2[b], p3[b])
        K = k_matrix(k)
        pose = pnp(q2, q3, K)
        reference = frame_error_and_depth(q2, q3, K, *pose)
        with native.using("c"):
            assert native.frame_error_and_depth(q2, q3, K, *pose) == reference, b


@needs_core
def test_the_error_and_depth_of_hostile_frames_are_the_references():
    rng = np.random.default_rng(12)
    x, X, _, rvec, tvec = random_frames(rng, frames=1, points=33)
    x, X, r, t = x[0], X[0], rvec[0], tvec[0]
    K = K_TEST.copy()
    cases = []
    nan_point = X.copy()
    nan_point[4, 1] = np.nan
    on_the_plane = X.copy()
    on_the_plane[5] = -(cv2_rotation(r).T @ t)  # the camera's centre: Z_C = 0
    cases += [(x, nan_point, r, t), (x, on_the_plane, r, t), (x, X, r * np.nan, t), (x, X, r, -t), (x[:1], X[:1], r, t)]
    skewed = K.copy()
    skewed[0, 1] = 0.7
    for q2, q3, rr, tt in cases:
        for K_case in (K, skewed):
            reference = frame_error_and_depth(q2, q3, K_case, rr, tt)
            with native.using("c"):
                got = native.frame_error_and_depth(q2, q3, K_case, rr, tt)
            assert np.array_equal(np.array(got), np.array(reference), equal_nan=True), (reference, got)


def cv2_rotation(rvec):
    import cv2

    return cv2.Rodrigues(rvec)[0]
