"""Which implementation runs the per-frame kernels: the compiled core or numpy.

The compiled core (``dimenet.runtime.native._core``, built from dimenet_*.c and _module*.c beside
this file by ``pip install .``) computes the feature stage of every encoder
(``rectify.features.grid_features``), the check stage's error and depth (``frame_error_and_depth``
below), stage pnp_k's Gauss-Newton pose under K (``pose_under_k``: ``geometry.pose_step``), SQPnP's unit
(``solve_pnp_start``) and validation's fast tests (``rectify.checks``); the numpy code stays the reference and
the fallback. The choice
is made once, at import:

- ``DIMENET_IMPLEMENTATION`` unset (or empty): "c" when the extension imports, else "python" (a
  machine without a compiler installs the pure-numpy package);
- ``DIMENET_IMPLEMENTATION=python``: numpy, whatever is built;
- ``DIMENET_IMPLEMENTATION=c``: the compiled core, an ImplementationError when it is not built;
- any other value: an ImplementationError.

``dimenet --version`` and ``dimenet bench`` print the one running. Tests and benchmarks switch it in
process with ``set_implementation`` (or ``using``, its context manager); an app has no reason to.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType
from typing import Optional

import numpy as np

from dimenet.runtime.errors import DimenetError
from dimenet.runtime.geometry import frame_error_and_depth as _frame_error_and_depth_reference
from dimenet.runtime.geometry import k_matrix
from dimenet.runtime.geometry import solve_pnp_start as _solve_pnp_start_reference
from dimenet.runtime.geometry.map_step import map_steps as _map_steps_reference
from dimenet.runtime.geometry.pose_step import POSE_STEPS
from dimenet.runtime.geometry.pose_step import pose_under_k as _pose_under_k_reference

ENV_VARIABLE = "DIMENET_IMPLEMENTATION"
IMPLEMENTATIONS = ("c", "python")


class ImplementationError(DimenetError):
    """DIMENET_IMPLEMENTATION names no implementation, or the compiled core it asks for is not built."""


def _compiled() -> tuple[Optional[ModuleType], Optional[str]]:
    """The extension module, or None and why it does not import."""
    try:
        from dimenet.runtime.native import _core
    except ImportError as exc:
        return None, str(exc)
    return _core, None


def _chosen(asked: Optional[str]) -> tuple[str, Optional[ModuleType]]:
    if asked not in (None, "", *IMPLEMENTATIONS):
        raise ImplementationError(
            f"{ENV_VARIABLE} must be one of {', '.join(IMPLEMENTATIONS)} (or unset: c when it is built), got {asked!r}"
        )
    if asked == "python":
        return "python", None
    module, why = _compiled()
    if module is None and asked == "c":
        raise ImplementationError(
            f"{ENV_VARIABLE}=c but the compiled core is not built ({why}); reinstall with a C compiler "
            f"(pip install . builds it) or set {ENV_VARIABLE}=python"
        )
    return ("c", module) if module is not None else ("python", None)


# The implementation running, and the extension module when it is "c" (None: numpy). Read per call
# by the kernels' callers (rectify.features); only set_implementation changes them.
IMPLEMENTATION, core = _chosen(os.environ.get(ENV_VARIABLE))


def implementation() -> str:
    """The implementation running: "c" or "python"."""
    return IMPLEMENTATION


def compiled_available() -> bool:
    """Whether the compiled core is built (whichever runs)."""
    return _compiled()[0] is not None


def set_implementation(name: str) -> None:
    """Run ``name`` ("c" or "python") from now on, in this process (tests and benchmarks);
    ImplementationError for another name or for "c" when it is not built. Not for use while other
    threads rectify."""
    global IMPLEMENTATION, core
    if name not in IMPLEMENTATIONS:
        raise ImplementationError(f"the implementation must be one of {', '.join(IMPLEMENTATIONS)}, got {name!r}")
    IMPLEMENTATION, core = _chosen(name)


@contextmanager
def using(name: str) -> Iterator[None]:
    """``set_implementation(name)`` inside a with block, the previous one restored after it."""
    previous = IMPLEMENTATION
    set_implementation(name)
    try:
        yield
    finally:
        set_implementation(previous)


def pose_under_k(points_2d, points_3d, k, rvec, tvec, steps: int = POSE_STEPS) -> tuple:
    """``geometry.pose_step.pose_under_k`` in the running implementation, the same numbers to the bit: the
    pose under k (4,) px after ``steps`` Gauss-Newton steps from rvec, tvec (3,), and the mean
    reprojection error (px) and smallest depth (mm) there -> (rvec, tvec, e, depth). points_2d (N, 2) px
    and points_3d (N, 3) mm float64. InputError when a step has no solution."""
    if core is None:
        return _pose_under_k_reference(points_2d, points_3d, k, rvec, tvec, steps)
    rvec_out, tvec_out = np.empty(3), np.empty(3)
    e, depth = _core_call(points_2d, points_3d, k_matrix(k), rvec, tvec, steps, rvec_out, tvec_out)
    return rvec_out, tvec_out, e, depth


def frame_error_and_depth(points_2d, points_3d, K, rvec, tvec) -> tuple[float, float]:
    """``geometry.frame_error_and_depth`` (one frame's mean reprojection error px under K (3, 3) at the pose
    rvec, tvec (3,), and its smallest depth mm) in the running implementation, to the bit: the core's pose
    kernel with no step (a K with skew: numpy). The check stage's e(K): BENCHMARKS.md has its us."""
    if core is None or K[0, 1] != 0.0:
        return _frame_error_and_depth_reference(points_2d, points_3d, K, rvec, tvec)
    return _core_call(points_2d, points_3d, K, rvec, tvec, 0, None, None)


def solve_pnp_start(points_2d, points_3d, K) -> tuple[np.ndarray, np.ndarray]:
    """``geometry.solve_pnp_start`` (SQPnP's pose {W}->{C} under K (3, 3) px of points_2d (N, 2) px and
    points_3d (N, 3) mm -> rvec, tvec (3,)) with its unit (``geometry.pnp.power_of_two_unit``) from the running
    implementation, the same to the bit: 1.4 against 5.1 us at 320 points (BENCHMARKS.md). InputError when
    there is no pose."""
    if core is None or not (isinstance(points_3d, np.ndarray) and points_3d.dtype == np.float64):
        return _solve_pnp_start_reference(points_2d, points_3d, K)
    try:  # validated points are (N, 3) float64, C-contiguous
        unit = core.power_of_two_unit(points_3d)
    except (TypeError, ValueError):  # another layout: the reference takes it as numpy would
        return _solve_pnp_start_reference(points_2d, points_3d, K)
    return _solve_pnp_start_reference(points_2d, points_3d, K, unit)


def error_at_pnp(points_2d, points_3d, K) -> float:
    """One frame's mean reprojection error (px) under K (3, 3) at its PnP pose (``geometry.solve_pnp_start``),
    ``frame_error_and_depth`` in the running implementation; InputError when there is no pose."""
    return frame_error_and_depth(points_2d, points_3d, K, *solve_pnp_start(points_2d, points_3d, K))[0]


def map_steps(
    points_2d, points_3d, k_prior, K_cov_prior, rvec, tvec, turn, noise_px, noise_floor_px, iterations
) -> tuple:
    """``geometry.map_step.map_steps`` (one frame's MAP Gauss-Newton steps over (pose, K): the arguments and the
    result are its) in the running implementation, the same numbers to the bit; the core takes one step
    (``dimenet_map_step``), more steps run in numpy. InputError when the prior's covariance or the Hessian is not
    positive definite."""
    if core is None or iterations != 1:
        return _map_steps_reference(
            points_2d, points_3d, k_prior, K_cov_prior, rvec, tvec, turn, noise_px, noise_floor_px, iterations
        )
    noise = -1.0 if noise_px is None else max(float(noise_px), noise_floor_px)  # the reference's floor; < 0: none
    k, R, tvec_out, cov, residuals = (
        np.empty(4),
        np.empty((3, 3)),
        np.empty(3),
        np.empty((10, 10)),
        np.empty((len(points_2d), 2)),
    )
    arrays = (points_2d, points_3d, k_prior, K_cov_prior, rvec, tvec, turn)
    try:  # the arrays as they come (the rectifier's are float64, C-contiguous)
        weight, e, depth, steps = core.map_step(*arrays, noise, noise_floor_px, k, R, tvec_out, cov, residuals)
    except TypeError:  # another type or layout: as numpy would take them
        arrays = [None if a is None else np.ascontiguousarray(a, np.float64) for a in arrays]
        weight, e, depth, steps = core.map_step(*arrays, noise, noise_floor_px, k, R, tvec_out, cov, residuals)
    return k, R, tvec_out, cov, weight, residuals, e, depth, steps


def _core_call(points_2d, points_3d, K, rvec, tvec, steps, rvec_out, tvec_out) -> tuple[float, float]:
    try:  # the arrays as they come (validated_frame's are float64, C-contiguous)
        return core.pose_steps(points_2d, points_3d, K, rvec, tvec, steps, rvec_out, tvec_out)
    except TypeError:  # another type or layout: as numpy would take them
        p2, p3 = np.ascontiguousarray(points_2d, np.float64), np.ascontiguousarray(points_3d, np.float64)
        K = np.ascontiguousarray(K, np.float64)
        r, t = (np.ascontiguousarray(a, np.float64).reshape(-1) for a in (rvec, tvec))
        return core.pose_steps(p2, p3, K, r, t, steps, rvec_out, tvec_out)
