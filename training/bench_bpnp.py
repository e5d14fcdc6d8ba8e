"""Benchmark of the BPnP layer: forward + backward of B frames x N points, single-threaded.

    dimenet bench --bpnp [--frames 32] [--points 320] [--repeats 200] [--baseline-repeats 10] [--json]

Times ``dimenet.training.bpnp.solve_pnp`` and, for scale, a BPnP_fast-style baseline
(see ``_BaselineBPnP``) on the same synthetic scene, and reports the median wall times.
"""

from __future__ import annotations

import statistics
import time

import cv2
import numpy as np
import torch

from dimenet.runtime import geometry as g
from dimenet.training.bpnp import solve_pnp

K_PHONE = np.array([[3000.0, 0.0, 2016.0], [0.0, 3000.0, 1512.0], [0.0, 0.0, 1.0]])


def _scene(frames: int, points: int, seed: int = 0):
    """Non-planar clouds (mm) 0.4-0.9 m in front of the camera, 0.4 px image noise: x, X, K, w (numpy)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-150.0, 150.0, (frames, points, 3))
    K = np.broadcast_to(K_PHONE, (frames, 3, 3)).copy()
    rvec = rng.normal(0.0, 0.2, (frames, 3))
    tvec = np.c_[rng.normal(0.0, 30.0, (frames, 2)), rng.uniform(400.0, 900.0, frames)]
    x = g.project(X, K, rvec, tvec) + rng.normal(0.0, 0.4, (frames, points, 2))
    return x, X, K, np.ones((frames, points))


def _rodrigues(rvec: torch.Tensor) -> torch.Tensor:
    """(3,) axis-angle (rad, non-zero) -> (3, 3) rotation, differentiable by autograd."""
    theta = rvec.norm()
    k = rvec / theta
    zero = torch.zeros((), dtype=rvec.dtype)
    S = torch.stack(
        [torch.stack([zero, -k[2], k[1]]), torch.stack([k[2], zero, -k[0]]), torch.stack([-k[1], k[0], zero])]
    )
    return torch.eye(3, dtype=rvec.dtype) + torch.sin(theta) * S + (1.0 - torch.cos(theta)) * (S @ S)


def _project(pose: torch.Tensor, X: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pixels (N, 2) of {W} points X (N, 3) mm under pose (rvec, tvec) (6,) and K (3, 3)."""
    p = (X @ _rodrigues(pose[:3]).T + pose[3:]) @ K.T
    return p[:, :2] / p[:, 2:]


class _BaselineBPnP(torch.autograd.Function):
    """BPnP_fast-style baseline, re-implemented: per-sample Python loop, float32,
    autograd-computed projection Jacobians via torch.autograd.functional.jacobian,
    Hessian via the Gauss-Newton approximation. Returns the pose (B, 6)."""

    @staticmethod
    def forward(ctx, x, X, K):
        poses = []
        for b in range(len(x)):
            _, r, t = cv2.solvePnP(
                X[b].double().numpy(), x[b].double().numpy(), K[b].double().numpy(), None, flags=cv2.SOLVEPNP_ITERATIVE
            )
            poses.append(np.r_[r.ravel(), t.ravel()])
        pose = torch.tensor(np.array(poses), dtype=torch.float32)
        ctx.save_for_backward(X, K, pose)
        return pose

    @staticmethod
    def backward(ctx, grad_pose):
        X, K, pose = ctx.saved_tensors
        grads = [], [], []
        for b in range(len(X)):
            J_pose, J_X, J_K = torch.autograd.functional.jacobian(_project, (pose[b], X[b], K[b]), vectorize=True)
            J_pose, J_X, J_K = (J.reshape(2 * len(X[b]), -1) for J in (J_pose, J_X, J_K))
            # Residual r = pi - x; g = J_pose^T r; Gauss-Newton: H = J^T J, dg/dtheta = J_pose^T dr/dtheta.
            Ju = J_pose @ torch.linalg.solve(J_pose.T @ J_pose, grad_pose[b])
            grads[0].append(Ju.reshape(-1, 2))
            grads[1].append(-(J_X.T @ Ju).reshape(-1, 3))
            grads[2].append(-(J_K.T @ Ju).reshape(3, 3))
        return tuple(torch.stack(grad) for grad in grads)


def _median_ms(step, repeats: int) -> float:
    """Median wall time (ms) of ``step()`` over ``repeats`` runs after one warm-up run."""
    step()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def run(frames: int, points: int, repeats: int, baseline_repeats: int) -> dict:
    """Median forward+backward times (ms) of the exact layer and of the baseline on one scene."""
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    x, X, K, w = (torch.from_numpy(a) for a in _scene(frames, points))
    upstream = torch.from_numpy(np.random.default_rng(1).normal(size=(frames, 6)))

    def exact():
        x_, X_, K_ = (v.clone().requires_grad_() for v in (x, X, K))
        rvec, tvec = solve_pnp(x_, X_, w, K_)
        (torch.cat([rvec, tvec], -1) * upstream).sum().backward()

    def baseline():
        inputs = [v.float().requires_grad_() for v in (x, X, K)]
        (_BaselineBPnP.apply(*inputs) * upstream.float()).sum().backward()

    ours = _median_ms(exact, repeats)
    base = _median_ms(baseline, baseline_repeats)
    return {
        "frames": frames,
        "points": points,
        "threads": 1,
        "repeats": repeats,
        "median_ms": ours,
        "baseline": "BPnP_fast-style baseline, re-implemented: per-sample Python loop, float32, "
        "autograd-computed projection Jacobians via torch.autograd.functional.jacobian, "
        "Hessian via the Gauss-Newton approximation",
        "baseline_repeats": baseline_repeats,
        "baseline_median_ms": base,
        "speedup": base / ours,
        "target_ms": 20.0,
    }


def format_report(result: dict) -> str:
    """The lines of the result of ``run``."""
    return "\n".join(
        [
            f"B={result['frames']} frames x N={result['points']} points, forward+backward, 1 thread",
            f"  exact BPnP (this package): median {result['median_ms']:.2f} ms over {result['repeats']} runs "
            f"(target <= {result['target_ms']:.0f} ms)",
            f"  {result['baseline']}: median {result['baseline_median_ms']:.1f} ms over {result['baseline_repeats']} "
            "runs",
            f"  speed-up: {result['speedup']:.1f}x",
        ]
    )
