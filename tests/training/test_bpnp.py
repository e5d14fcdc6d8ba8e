"""The batched exact BPnP layer: pose vs OpenCV, implicit gradients vs re-solved finite differences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")  # the base-only install has no torch: skip, not fail

from helpers import random_frames

from dimenet.runtime import geometry as g
from dimenet.runtime.errors import InputError
from dimenet.training import bpnp

K_PHONE = np.array([[3000.0, 0.0, 2016.0], [0.0, 3000.0, 1512.0], [0.0, 0.0, 1.0]])
# Bound on the relative error of an implicit gradient vs finite differences of the re-solved PnP.
GRAD_RTOL = 1e-6


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    """The tensors here are tiny: one thread avoids multi-ms BLAS stalls when the CPU is oversubscribed."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _scene(seed, frames=2, points=10, noise_px=0.4, planar=False):
    """float64 tensors x (B, N, 2) px, X (B, N, 3) mm, K (B, 3, 3), w (B, N) of a noisy synthetic scene."""
    x, X, K, _, _ = random_frames(np.random.default_rng(seed), frames, points, noise_px, K=K_PHONE, planar=planar)
    return (
        torch.from_numpy(x),
        torch.from_numpy(X),
        torch.from_numpy(K),
        torch.ones(frames, points, dtype=torch.float64),
    )


def _pose(x, X, K, w):
    return torch.cat(bpnp.solve_pnp(x, X, w, K), -1)  # (B, 6): rvec rad, tvec mm


def _implicit_jacobians(x, X, K, w):
    """d pose / d (x, X, K) of each frame from the layer's backward: three (B, 6, ...) tensors."""
    inputs = [v.clone().requires_grad_() for v in (x, X, K)]
    pose = _pose(*inputs, w)
    rows = [torch.autograd.grad(pose[:, k].sum(), inputs, retain_graph=True) for k in range(6)]
    return [torch.stack([row[i] for row in rows], 1) for i in range(3)]


def _fd_jacobian(x, X, K, w, which, frame, entries, h):
    """Central differences (6, len(entries)) of frame's re-solved pose w.r.t. flat entries of input ``which``."""
    cols = []
    for j in entries:
        ends = []
        for sign in (1.0, -1.0):
            inputs = [x.clone(), X.clone(), K.clone()]
            inputs[which][frame].view(-1)[j] += sign * h
            ends.append(_pose(*inputs, w)[frame])
        cols.append((ends[0] - ends[1]) / (2.0 * h))
    return torch.stack(cols, -1)


def _relative_error(approx, exact):
    """Per pose component: max abs error over the inputs over the largest |derivative| of that component."""
    return ((approx - exact).abs().amax(-1) / exact.abs().amax(-1)).max().item()


def _rotation_angle(rvec_a, rvec_b):
    """Angle (rad) of R(a)^T R(b), from its skew part (accurate for tiny angles, unlike cv2.Rodrigues)."""
    D = g.rvec_to_matrix(rvec_a).T @ g.rvec_to_matrix(rvec_b)
    return 0.5 * np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])


def _opencv_pose(x, X, K):
    _, r, t = cv2.solvePnP(X, x, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
    r, t = cv2.solvePnPRefineLM(X, x, K, None, r, t)
    return r.ravel(), t.ravel()


def test_gradcheck_points_and_k():
    x, X, K, w = _scene(seed=1, frames=2, points=8)
    w[1, 3] = 2.5  # a non-uniform weight
    inputs = tuple(v.clone().requires_grad_() for v in (x, X, K))
    # Tight tolerances: d rvec / d x is ~1e-4 rad/px, so the default atol=1e-5 would prove nothing.
    assert torch.autograd.gradcheck(lambda a, b, c: bpnp.solve_pnp(a, b, w, c), inputs, eps=1e-4, atol=1e-9, rtol=1e-6)


@pytest.mark.parametrize("which, h", [(0, 1e-2), (1, 1e-2), (2, 0.5)])
def test_gradient_matches_finite_differences_of_the_resolved_pnp(which, h):
    # 0.4 px noise leaves residuals, so the second-order terms of the exact Hessian matter:
    # with the Gauss-Newton Hessian this error is ~2e-4 here.
    x, X, K, w = _scene(seed=2, frames=2, points=10)
    exact = _implicit_jacobians(x, X, K, w)[which]
    entries = [0, 4, 2, 5] if which == 2 else range(x[0].numel() if which == 0 else X[0].numel())  # fx fy cx cy
    for frame in range(2):
        fd = _fd_jacobian(x, X, K, w, which, frame, entries, h)
        assert _relative_error(fd, exact[frame].reshape(6, -1)[:, list(entries)]) <= GRAD_RTOL
    if which == 2:  # K entries other than fx, fy, cx, cy are not read: zero gradient
        assert torch.all(exact.reshape(2, 6, 9)[..., [1, 3, 6, 7, 8]] == 0)


def test_gradient_near_zero_and_half_turn_rotations():
    x, X, K, w = _scene(seed=3, frames=2, points=10, noise_px=0.0)
    tvec = np.array([[10.0, -20.0, 600.0], [-15.0, 5.0, 700.0]])
    rvecs = np.array([[1e-7, -2e-7, 1e-7], (np.pi - 1e-4) * np.array([0.6, -0.8, 0.0])])
    for b in range(2):
        x[b] = torch.from_numpy(g.project(X[b].numpy(), K[b].numpy(), rvecs[b], tvec[b]))
    x += torch.from_numpy(np.random.default_rng(4).normal(0, 0.4, x.shape))
    pose = _pose(x, X, K, w)
    exact = _implicit_jacobians(x, X, K, w)[0]
    for b in range(2):
        r_cv, t_cv = _opencv_pose(x[b].numpy(), X[b].numpy(), K[b].numpy())
        # OpenCV's LM (Rodrigues parameters) stops short near a half-turn: on OpenCV 5.1 it ends
        # 2e-8 rad from ours with a 5e-10 px^2 larger cost, so: the same pose, and ours no worse.
        assert _rotation_angle(pose[b, :3].numpy(), r_cv) <= 1e-6
        cost, cost_cv = (
            (g.reprojection_errors(x[b].numpy(), X[b].numpy(), K[b].numpy(), r, t) ** 2).sum()
            for r, t in ((pose[b, :3].numpy(), pose[b, 3:].numpy()), (r_cv, t_cv))
        )
        assert cost <= cost_cv + 1e-12
        fd = _fd_jacobian(x, X, K, w, 0, b, range(20), 1e-3)
        assert _relative_error(fd, exact[b].reshape(6, -1)) <= GRAD_RTOL
    assert np.linalg.norm(pose[1, :3]) > np.pi - 2e-4  # the half-turn branch of the log was used


def test_pose_matches_opencv_iterative_plus_refine_lm():
    x, X, K, w = _scene(seed=5, frames=3, points=40)
    xp, Xp, Kp, wp = _scene(seed=6, frames=1, points=40, planar=True)
    x, X, K, w = (torch.cat(pair) for pair in ((x, xp), (X, Xp), (K, Kp), (w, wp)))
    pose = _pose(x, X, K, w).numpy()
    for b in range(4):
        r_cv, t_cv = _opencv_pose(x[b].numpy(), X[b].numpy(), K[b].numpy())
        assert _rotation_angle(pose[b, :3], r_cv) <= 1e-8
        np.testing.assert_allclose(pose[b, 3:], t_cv, atol=1e-5)
        # At least as good an optimum as OpenCV's.
        cost = g.reprojection_errors(x[b].numpy(), X[b].numpy(), K[b].numpy(), pose[b, :3], pose[b, 3:]) ** 2
        cost_cv = g.reprojection_errors(x[b].numpy(), X[b].numpy(), K[b].numpy(), r_cv, t_cv) ** 2
        assert cost.sum() <= cost_cv.sum() + 1e-9


def test_integer_weights_equal_repeated_points_in_opencv():
    x, X, K, w = _scene(seed=7, frames=2, points=20)
    w = torch.from_numpy(np.random.default_rng(8).integers(1, 4, (2, 20)).astype(np.float64))
    pose = _pose(x, X, K, w).numpy()
    for b in range(2):
        reps = w[b].numpy().astype(int)
        r_cv, t_cv = _opencv_pose(np.repeat(x[b].numpy(), reps, 0), np.repeat(X[b].numpy(), reps, 0), K[b].numpy())
        assert _rotation_angle(pose[b, :3], r_cv) <= 1e-8
        np.testing.assert_allclose(pose[b, 3:], t_cv, atol=1e-5)


def test_batch_equals_frames_solved_alone():
    x, X, K, w = _scene(seed=9, frames=3, points=12)
    K[1, 0, 2] += 40.0  # frames with different K
    w[2, :3] = 0.0
    w[0, 5] = 3.0
    upstream = torch.from_numpy(np.random.default_rng(10).normal(size=(3, 6)))

    def solve_and_grad(x, X, K, w):
        inputs = [v.clone().requires_grad_() for v in (x, X, K)]
        pose = _pose(*inputs, w)
        return pose.detach(), torch.autograd.grad((pose * upstream[: len(x)]).sum(), inputs)

    pose, grads = solve_and_grad(x, X, K, w)
    for b in range(3):
        upstream_b = upstream[b : b + 1]
        inputs = [v[b : b + 1].clone().requires_grad_() for v in (x, X, K)]
        pose_b = _pose(*inputs, w[b : b + 1])
        grads_b = torch.autograd.grad((pose_b * upstream_b).sum(), inputs)
        torch.testing.assert_close(pose_b[0].detach(), pose[b], rtol=1e-12, atol=1e-12)
        for gb, gall in zip(grads_b, grads):
            torch.testing.assert_close(gb[0], gall[b], rtol=1e-10, atol=1e-15)


def test_masked_points_have_no_effect_and_zero_gradient():
    x, X, K, w = _scene(seed=11, frames=2, points=14)
    w[:, 10:] = 0.0
    pose_kept, grads_kept = _pose_and_grads(x[:, :10], X[:, :10], K, w[:, :10])
    for garbage_2d, garbage_3d in ((1e9, -1e6), (float("nan"), float("inf"))):
        x_bad, X_bad = x.clone(), X.clone()
        x_bad[:, 10:] = garbage_2d
        X_bad[:, 10:, 2] = garbage_3d  # behind the camera / not finite
        pose, grads = _pose_and_grads(x_bad, X_bad, K, w)
        torch.testing.assert_close(pose, pose_kept, rtol=1e-12, atol=1e-12)
        assert torch.all(grads[0][:, 10:] == 0) and torch.all(grads[1][:, 10:] == 0)
        for full, kept in zip((grads[0][:, :10], grads[1][:, :10], grads[2]), grads_kept):
            torch.testing.assert_close(full, kept, rtol=1e-9, atol=1e-15)


def _pose_and_grads(x, X, K, w):
    """Pose (B, 6) and the gradients of sum(pose) w.r.t. x, X, K."""
    inputs = [v.clone().requires_grad_() for v in (x, X, K)]
    pose = _pose(*inputs, w)
    return pose.detach(), torch.autograd.grad(pose.sum(), inputs)


def _spoil(kind, x, X, K, w):
    """Make frame 1 of a scene singular in the given way."""
    if kind == "three points":
        w[1, 3:] = 0.0
    elif kind == "collinear 3D points":
        X[1] = torch.linspace(0, 1, X.shape[1], dtype=torch.float64)[:, None] * torch.tensor([100.0, 50.0, 20.0])
    elif kind == "coincident 2D points":
        x[1] = x[1, :1]
    elif kind == "nan in a weighted point":
        X[1, 4, 0] = float("nan")
    elif kind == "infinite K":
        K[1, 0, 0] = float("inf")
    elif kind == "zero focal length":
        K[1, 0, 0] = 0.0


@pytest.mark.parametrize(
    "kind",
    [
        "three points",
        "collinear 3D points",
        "coincident 2D points",
        "nan in a weighted point",
        "infinite K",
        "zero focal length",
    ],
)
def test_singular_frame_raises_input_error_naming_it(kind):
    x, X, K, w = _scene(seed=12, frames=3, points=10)
    _spoil(kind, x, X, K, w)
    with pytest.raises(InputError, match="frame 1"):
        bpnp.solve_pnp(x.requires_grad_(), X, w, K)


def test_singular_hessian_is_caught_after_the_solve():
    # A rank-deficient exact Hessian (one pose direction unobservable) is rejected, not inverted.
    H = torch.eye(6, dtype=torch.float64).repeat(2, 1, 1)
    H[1, 5, 5] = 0.0
    with pytest.raises(InputError, match="frame 1"):
        bpnp._check_hessian(H)
    bpnp._check_hessian(H[:1])


@pytest.mark.parametrize("bad", ["float32", "shape"])
def test_bad_dtype_or_shape_raises(bad):
    x, X, K, w = _scene(seed=13, frames=1, points=8)
    if bad == "float32":
        x = x.float()
    else:
        X = X[:, :7]
    with pytest.raises(InputError):
        bpnp.solve_pnp(x, X, w, K)


def test_project_matches_runtime_geometry_and_is_differentiable():
    from dimenet.runtime import geometry as g
    from dimenet.training.bpnp import project

    rng = np.random.default_rng(11)
    x, X, K, rvec, tvec = random_frames(rng, frames=2, points=7)
    args = [torch.from_numpy(a).requires_grad_() for a in (X, K, rvec, tvec)]
    out = project(*args)
    np.testing.assert_allclose(out.detach().numpy(), g.project(X, K, rvec, tvec), atol=1e-9)
    assert torch.autograd.gradcheck(project, args, eps=1e-6, atol=1e-6)


def test_bench_bpnp_is_the_training_bench_the_runtime_finds_by_its_entry_point(capsys):
    from dimenet.runtime.cli.main import main
    from dimenet.runtime.plugins import entry_points

    assert entry_points("dimenet.benches")["bpnp"].value == "dimenet.training.bench_bpnp"
    argv = ["bench", "--bpnp", "--frames", "2", "--points", "12", "--repeats", "1", "--baseline-repeats", "1"]
    assert main(argv) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "B=2 frames x N=12 points, forward+backward, 1 thread" and "exact BPnP" in out[1], out
