"""Mode map's step in the compiled core (``dimenet_map_step``) against its numpy reference
(``geometry.map_step.map_steps``), to the bit: the MAP K, pose, posterior, weight, residuals, their mean norm,
the smallest depth and steps of one Gauss-Newton step, with the prior's own noise estimate and with a known
noise, turned and not; the same InputError where the points fix no pose or the prior's covariance is not
positive definite; and ``Rectifier.rectify`` in mode map on the bench's frames, the same results and fallbacks
under both implementations."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import native
from dimenet.runtime.bench.latency import bench_frames, bench_rectifier
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import k_params
from dimenet.runtime.geometry.map_step import map_steps
from dimenet.runtime.rectify.map_fit import NOISE_FLOOR_PX
from dimenet.runtime.rectify.model import load_model

needs_core = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")
BENCH_FRAMES = 300


def both_steps(*args):
    """native.map_steps (one step) under numpy, then under the compiled core."""
    out = []
    for name in ("python", "c"):
        with native.using(name):
            out.append(native.map_steps(*args, NOISE_FLOOR_PX, 1))
    return out


def assert_bit_identical(reference: tuple, compiled: tuple) -> None:
    for a, b in zip(reference, compiled):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def frame_prior(rng, k_true, sigma_px: float):
    """A network-like prior: k_true moved by sigma_px noise, its covariance (4, 4) px^2 with correlations."""
    k_prior = k_true + rng.normal(0.0, sigma_px, 4)
    A = rng.normal(0.0, 0.3, (4, 4)) + np.eye(4)
    return k_prior, A @ A.T * sigma_px**2


@needs_core
@pytest.mark.parametrize("planar", [False, True])
def test_the_core_takes_the_references_step_to_the_bit(planar):
    rng = np.random.default_rng(7 + planar)
    x, X, K, rvec, tvec = random_frames(rng, frames=40, points=90, noise_px=0.8, planar=planar)
    taken = 0
    for b in range(len(x)):
        k_prior, prior_cov = frame_prior(rng, k_params(K[b]), sigma_px=rng.choice([0.5, 5.0, 50.0]))
        start = rvec[b] + rng.normal(0.0, 1e-3, 3), tvec[b] + rng.normal(0.0, 0.5, 3)
        turn = rng.normal(0.0, 2e-3, 3) if b % 2 else None
        noise_px = None if b % 3 else float(rng.uniform(0.05, 2.0))
        reference, compiled = both_steps(x[b], X[b], k_prior, prior_cov, *start, turn, noise_px)
        assert_bit_identical(reference, compiled)
        _, R, t, _, _, residuals, e, depth, steps = compiled
        assert e == pytest.approx(np.hypot(*residuals.T).mean(), rel=1e-12)
        assert depth == pytest.approx((X[b] @ R[2] + t[2]).min(), rel=1e-12)
        taken += steps
    assert taken >= len(x) // 2  # most steps are taken: what is compared is a moved K and pose


@needs_core
def test_a_step_that_raises_the_cost_is_refused_alike():
    # From a start 1 rad off, the one step overshoots (tests/rectify/test_map_fit.py's case).
    x, X, K, rvec, tvec = random_frames(np.random.default_rng(0), frames=1, points=60, noise_px=0.5)
    k_prior, prior_cov = k_params(K[0]), np.eye(4) * 25.0
    reference, compiled = both_steps(x[0], X[0], k_prior, prior_cov, rvec[0] + [1.0, 0.0, 0.0], tvec[0], None, None)
    assert reference[-1] == 0
    assert_bit_identical(reference, compiled)
    np.testing.assert_array_equal(reference[0], k_prior)  # the start is returned


@needs_core
@pytest.mark.parametrize(
    "case, words",
    [("line", "fix no pose"), ("negative variance", "prior's covariance"), ("singular", "prior's covariance")],
)
def test_no_pose_or_a_bad_prior_raise_the_same_input_error(case, words):
    rng = np.random.default_rng(4)
    x, X, K, rvec, tvec = random_frames(rng, frames=1, points=30, noise_px=0.5)
    points_3d, prior_cov = X[0], np.eye(4) * 25.0
    if case == "line":  # the widest prior a double holds: the data alone, which fixes no pose
        points_3d, prior_cov = X[0][:1] + np.linspace(0.0, 1.0, 30)[:, None] * (X[0][1] - X[0][0]), np.eye(4) * 1e300
    elif case == "negative variance":
        prior_cov[2, 2] = -1.0
    else:
        prior_cov[3] = prior_cov[2]
        prior_cov[:, 3] = prior_cov[:, 2]
    messages = []
    for name in ("python", "c"):
        with native.using(name), pytest.raises(InputError) as error:
            native.map_steps(x[0], points_3d, k_params(K[0]), prior_cov, rvec[0], tvec[0], None, None, 0.1, 1)
        messages.append(str(error.value))
    assert messages[0] == messages[1] and words in messages[0]


@needs_core
def test_the_binding_refuses_arrays_of_the_wrong_kind():
    rng = np.random.default_rng(5)
    x, X, K, rvec, tvec = random_frames(rng, frames=1, points=20, noise_px=0.5)
    core, k = native._compiled()[0], k_params(K[0])
    outs = np.empty(4), np.empty((3, 3)), np.empty(3), np.empty((10, 10)), np.empty((20, 2))
    args = [x[0], X[0], k, np.eye(4), rvec[0], tvec[0], None, -1.0, 0.1, *outs]
    weight, e, depth, steps = core.map_step(*args)
    assert weight > 0 and e > 0 and depth > 0 and steps in (0, 1)
    with pytest.raises(ValueError, match="residuals_out"):
        core.map_step(*args[:-1], np.empty((19, 2)))
    with pytest.raises(TypeError, match="k_cov_prior"):
        core.map_step(*args[:3], np.eye(4, dtype=np.float32), *args[4:])
    with pytest.raises(ValueError, match="N >= 1"):
        core.map_step(x[0][:0], X[0][:0], *args[2:-1], np.empty((0, 2)))
    with pytest.raises(TypeError, match="14 arguments"):
        core.map_step(*args[:-1])


@needs_core
def test_mode_map_rectifies_the_bench_frames_alike():
    rect = bench_rectifier(load_model("default"), "map")
    p2, p3 = bench_frames(BENCH_FRAMES, 320, rect.image_size)
    results = {}
    for name in ("python", "c"):
        with native.using(name):
            results[name] = [rect.rectify(a, b) for a, b in zip(p2, p3)]
    notes = 0
    for i, (a, b) in enumerate(zip(results["python"], results["c"])):
        assert (a.fallback, a.fallback_code) == (b.fallback, b.fallback_code), i
        for u, v in ((a.K, b.K), (a.rvec, b.rvec), (a.tvec, b.tvec), (a.K_cov, b.K_cov)):
            np.testing.assert_array_equal(u, v, err_msg=f"bench frame {i}")
        notes += a.fallback is not None
    assert notes < BENCH_FRAMES  # MAP's own K stands on most frames: the core's step is what is compared


def test_more_steps_than_one_run_the_reference_under_either_implementation():
    # The core takes one step; native.map_steps hands more to numpy, so both implementations agree on them too.
    rng = np.random.default_rng(6)
    x, X, K, rvec, tvec = random_frames(rng, frames=1, points=50, noise_px=0.5, K=K_TEST)
    k_prior, prior_cov = k_params(K[0]) + [20.0, -15.0, 8.0, -6.0], np.eye(4) * 1e4
    args = (x[0], X[0], k_prior, prior_cov, rvec[0], tvec[0], None, None, NOISE_FLOOR_PX, 4)
    want = map_steps(*args)
    assert want[-1] > 1  # more than the core's one step was taken
    for name in ("python", "c") if native.compiled_available() else ("python",):
        with native.using(name):
            assert_bit_identical(native.map_steps(*args), want)
