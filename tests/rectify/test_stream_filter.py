"""rectify.stream_filter: the stream's Kalman step. The compiled core (``dimenet_stream_step``) against the plain-float
reference to the bit (carried, reset, jumps, covariances that are not positive definite, NaN evidence); the reference
against the textbook filter in numpy (LU solves) to rounding and against a hand-computed update; its refusals."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime import native
from dimenet.runtime.rectify.stream_filter import stream_step

TAU_S = np.array([30.0, 30.0, 0.6, 0.6])


def spd(rng, scale):
    A = rng.normal(size=(4, 4))
    return A @ A.T * scale + np.eye(4) * 1e-3


def cases(rng):
    k_c = np.array([3000.0, 3000.0, 2000.0, 1500.0])
    Q = np.diag([25.0, 25.0, 400.0, 400.0])
    for i in range(300):
        k = k_c + rng.normal(0.0, 10.0, 4)
        z = k + rng.normal(0.0, 10.0 ** rng.uniform(-1, 2), 4)
        R = spd(rng, 10.0 ** rng.uniform(-1, 3))
        if i % 25 == 0:
            R[2, 2] = np.nan  # evidence with a NaN: not positive definite
        elif i % 25 == 1:
            R = -np.eye(4)  # not positive definite
        elif i % 25 == 2:
            z[1] = np.nan
        dt_s = float(rng.choice([0.0, 1 / 30, 1 / 60, 0.2, 5.0]))
        yield k, spd(rng, 10.0 ** rng.uniform(-1, 2)), k_c + rng.normal(0.0, 2.0, 4), k_c, z, R, Q, dt_s, i % 7 == 0


def both(*args, chi2_limit=30.0):
    out = {}
    for name in ("c", "python"):
        with native.using(name):
            out[name] = stream_step(*args[:7], TAU_S, *args[7:], chi2_limit)
    return out["c"], out["python"]


@pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")
def test_the_core_gives_the_reference_to_the_bit():
    rng = np.random.default_rng(51)
    seen = {"jumped": 0, "not updated": 0, "reset": 0}
    for case in cases(rng):
        c, py = both(*case)
        np.testing.assert_array_equal(c.k, py.k)
        np.testing.assert_array_equal(c.P, py.P)
        assert (c.jumped, c.updated) == (py.jumped, py.updated)
        seen["jumped"] += c.jumped
        seen["not updated"] += not c.updated
        seen["reset"] += case[-1]
    assert min(seen.values()) >= 10, seen  # every branch is taken


def textbook(k, P, k_prior_last, k0, z, R, Q, dt_s, reset, chi2_limit=30.0):
    """The 0.9.3 stream's numpy filter: LU solves, matrix products."""
    if reset:
        k, P = k0.copy(), Q.copy()
    else:
        a = np.exp(-dt_s / TAU_S)
        A = np.outer(a, a)
        k, P = k0 + a * (k - k_prior_last), A * P + (1.0 - A) * Q
    S, innovation = P + R, z - k
    if not reset and innovation @ np.linalg.solve(S, innovation) > chi2_limit:
        k, P = k0.copy(), Q.copy()
        S, innovation = P + R, z - k
    gain = np.linalg.solve(S.T, P.T).T
    P = (np.eye(4) - gain) @ P
    return k + gain @ innovation, (P + P.T) / 2.0


def test_the_reference_is_the_textbook_filter():
    rng = np.random.default_rng(5)
    compared = 0
    with native.using("python"):
        for case in cases(rng):
            step = stream_step(*case[:7], TAU_S, *case[7:], 30.0)
            if not step.updated or np.isnan(case[4]).any():
                continue
            k, P = textbook(*case)
            np.testing.assert_allclose(step.k, k, rtol=0, atol=1e-9 * np.abs(k).max())
            np.testing.assert_allclose(step.P, P, rtol=0, atol=1e-9 * np.abs(P).max())
            compared += 1
    assert compared > 200


def test_a_reset_update_by_hand_and_its_refusals():
    k0, z = np.array([100.0, 100.0, 50.0, 40.0]), np.array([104.0, 98.0, 50.0, 46.0])
    with native.using("python"):
        step = stream_step(np.zeros(4), np.eye(4), k0, k0, z, np.eye(4), np.eye(4), TAU_S, -1.0, True, 30.0)
        np.testing.assert_allclose(step.k, (k0 + z) / 2, rtol=1e-15)  # equal variances: the mean
        np.testing.assert_allclose(step.P, np.eye(4) / 2, rtol=1e-15)
        # carried without evidence where S is not positive definite
        step = stream_step(k0 + 2.0, np.eye(4), k0, k0, z, -2 * np.eye(4), np.eye(4), TAU_S, 0.0, False, 30.0)
        assert not step.updated and not step.jumped
        np.testing.assert_array_equal(step.k, k0 + 2.0)
        # a jump: the innovation (-16, -22, -20, -14) under S = 2 I, 668, beyond 30 resets the state before the update
        step = stream_step(k0 + 20.0, np.eye(4), k0, k0, z, np.eye(4), np.eye(4), TAU_S, 0.0, False, 30.0)
        assert step.jumped
        np.testing.assert_allclose(step.k, (k0 + z) / 2, rtol=1e-15)
    for name in ("c", "python") if native.compiled_available() else ("python",):
        with native.using(name), pytest.raises(ValueError, match="dt_s must be >= 0"):
            stream_step(k0, np.eye(4), k0, k0, z, np.eye(4), np.eye(4), TAU_S, -0.1, False, 30.0)


@pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")
def test_the_binding_refuses_bad_arrays():
    core = native._compiled()[0]
    v, M = np.zeros(4), np.eye(4)
    args = [v, M, v, v, v, M, M, TAU_S, 0.1, False, 30.0, np.empty(4), np.empty((4, 4))]
    assert core.stream_step(*args) == (False, True)
    with pytest.raises(ValueError):
        core.stream_step(np.zeros(3), *args[1:])
    with pytest.raises(TypeError, match="P_out"):
        core.stream_step(*args[:-1], np.empty((4, 4)).T)
    with pytest.raises(ValueError, match="dt_s"):
        core.stream_step(*args[:8], -1.0, *args[9:])
    with pytest.raises(TypeError, match="13 arguments"):
        core.stream_step(*args[:-1])
