"""One ``Rectifier`` shared by 8 caller threads gives every field of every result bit for bit as serial
calls do, for both bundled models, through ``rectify`` and ``rectify_batch`` (issue 48, failure 6).

The frames: the simulated rig and natural frames of conftest.py's ``frames``, each at a few point counts
(the reductions' lengths vary), and some with 60 px of noise (beyond the model's range: they fall back to
K_c). Each frame runs REPEATS times across the threads: a difference in the last bit that depends on where
a thread's buffers lie shows on some of them.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from helpers import example_camera

from dimenet.runtime.rectify.model import MODEL_NAMES
from dimenet.runtime.rectify.rectifier import Rectifier

THREADS = 8
REPEATS = 2
NOISY_EVERY = 9  # every 9th frame gets 60 px of noise and falls back


@pytest.fixture(scope="module")
def varied(frames):
    """(points_2d, points_3d) of ~700 frames: each simulated frame whole and two random subsets of 8 to 40
    of its points (with few points, a last-bit change in one point's error more often reaches the mean)."""
    rng = np.random.default_rng(48)
    size = np.array(frames.image_size, dtype=np.float64) - 1.0
    out = []
    for b in range(len(frames.points_2d)):
        valid = np.flatnonzero(frames.valid[b])
        subsets = [rng.choice(valid, int(rng.integers(8, 41)), replace=False) for _ in range(2)]
        for keep in [valid, *subsets]:
            p2, p3 = frames.points_2d[b][keep], frames.points_3d[b][keep]
            if len(out) % NOISY_EVERY == 0:
                p2 = np.clip(p2 + rng.normal(0.0, 60.0, p2.shape), 0.0, size)
            out.append((np.ascontiguousarray(p2), np.ascontiguousarray(p3)))
    return out


@pytest.fixture(scope="module", params=MODEL_NAMES)
def rectifier(request):
    camera = example_camera()
    return Rectifier.load(request.param, K_c=camera.K, image_size=camera.image_size)


def fields(result, b=None) -> tuple:
    """Every field of a result (of frame ``b`` of a batch's) as bytes; K_cov computed here, in the caller's thread."""
    arrays = (result.K, result.rvec, result.tvec, result.reprojection_error_px, result.reprojection_error_kc_px)
    arrays += (result.delta_k, result.K_cov)
    fallback = result.fallback
    if b is not None:
        arrays, fallback = tuple(None if a is None else a[b] for a in arrays), fallback[b]
    return tuple(None if a is None else np.asarray(a, np.float64).tobytes() for a in arrays) + (fallback,)


def assert_same(threaded: list, serial: list) -> None:
    names = ("K", "rvec", "tvec", "reprojection_error_px", "reprojection_error_kc_px", "delta_k", "K_cov", "fallback")
    differ = {}
    for got, expected in zip(threaded, serial):
        for name, a, b in zip(names, got, expected):
            differ[name] = differ.get(name, 0) + (a != b)
    assert not any(differ.values()), f"of {len(threaded)} results, these many differ from serial calls: {differ}"


def test_rectify_in_threads_is_bit_identical_to_serial(rectifier, varied):
    serial = [fields(rectifier.rectify(p2, p3)) for p2, p3 in varied]
    assert sum(f[-1] is not None for f in serial) >= len(varied) // NOISY_EVERY  # frames that fall back
    jobs = list(range(len(varied))) * REPEATS
    with ThreadPoolExecutor(THREADS) as pool:
        threaded = list(pool.map(lambda i: fields(rectifier.rectify(*varied[i])), jobs))
    assert_same(threaded, [serial[i] for i in jobs])


def test_rectify_batch_in_threads_is_bit_identical_to_serial(rectifier, varied):
    # batches of 8 frames, NaN-padded to the longest, as an app would send them
    batches = []
    for start in range(0, len(varied), 8):
        group = varied[start : start + 8]
        P = max(len(p2) for p2, _ in group)
        p2 = np.full((len(group), P, 2), np.nan)
        p3 = np.full((len(group), P, 3), np.nan)
        valid = np.zeros((len(group), P), bool)
        for b, (x, X) in enumerate(group):
            p2[b, : len(x)], p3[b, : len(x)], valid[b, : len(x)] = x, X, True
        batches.append((p2, p3, valid))

    def run(i: int) -> list:
        r = rectifier.rectify_batch(*batches[i])
        return [fields(r, b) for b in range(len(r.fallback))]

    serial = [run(i) for i in range(len(batches))]
    jobs = list(range(len(batches))) * REPEATS
    with ThreadPoolExecutor(THREADS) as pool:
        threaded = list(pool.map(run, jobs))
    assert_same([f for fs in threaded for f in fs], [f for i in jobs for f in serial[i]])
