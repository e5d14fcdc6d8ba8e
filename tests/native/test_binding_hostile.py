"""Every entry point of the compiled core's CPython binding, called as the runtime calls it (arguments recorded
from a rectify in both modes, a batch and a stream), then with each argument in turn replaced by a hostile value:
another dtype, shape or layout, a read-only or empty array, an array of the wrong length, non-finite values, None,
a scalar, a huge int, a string or a buffer. Each call must return or raise TypeError, ValueError or OverflowError;
a crash of the binding ends the test run. After them the recorded call still gives its first result."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import default_rectifier

from dimenet.runtime import native

pytestmark = pytest.mark.skipif(native.core is None, reason="the compiled core is not running (not built, or python)")
ENTRY_POINTS = (
    "frame_checks",
    "frame_features",
    "grid_features",
    "map_posterior",
    "map_step",
    "network_covariance",
    "occupied_cells",
    "pose_steps",
    "power_of_two_unit",
    "stream_step",
)


class _Recorder:
    """The core with each entry point's first call recorded (its arguments, copied)."""

    def __init__(self, core) -> None:
        self.core, self.calls = core, {}

    def __getattr__(self, name):
        function = getattr(self.core, name)
        if name not in ENTRY_POINTS:
            return function

        def recorded(*args):
            self.calls.setdefault(name, [a.copy() if isinstance(a, np.ndarray) else a for a in args])
            return function(*args)

        return recorded


@pytest.fixture(scope="module")
def calls():
    from dimenet.runtime.assets import asset
    from dimenet.runtime.formats.dataset import read_dataset

    core = native.core
    recorder = _Recorder(core)
    frames = read_dataset(asset("example_frames.npz"))
    x, X, m = frames.points_2d, frames.points_3d, frames.valid
    native.core = recorder
    try:
        for mode in ("dimenet", "map"):
            rect = default_rectifier(mode)
            res = rect.rectify(x[0][m[0]], X[0][m[0]])
            assert res.K_cov is not None
        rect.rectify_batch(x[:3], X[:3], m[:3])
        stream = rect.stream()
        for i in range(3):
            stream.update(x[i][m[i]], X[i][m[i]], i * 33_333_333)
    finally:
        native.core = core
    assert sorted(recorder.calls) == sorted(ENTRY_POINTS), "an entry point the runtime no longer calls"
    return recorder.calls


def _hostile(value, rng):
    if isinstance(value, np.ndarray):
        with np.errstate(invalid="ignore", over="ignore"):  # NaN and 1e308 cast to int64 and float32 as they may
            casts = (value.astype(np.float32), value.astype(np.int64))
        yield from casts
        yield value.astype(object)
        yield value.astype(complex)
        if value.ndim:
            yield value[:0]
            yield value[:1]
            yield value[::2]
            yield value.T
            yield value[None]
            yield value.ravel()
            yield np.asfortranarray(value)
            yield np.zeros((len(value) * 7 + 3,) + value.shape[1:], value.dtype)
        frozen = value.copy()
        frozen.setflags(write=False)
        yield frozen
        if value.dtype.kind == "f" and value.size:
            for bad in (np.nan, np.inf, -np.inf, 1e308, 5e-324):
                edited = value.copy()
                edited.flat[rng.integers(value.size)] = bad
                yield edited
    yield from (None, 3, -1, 2**70, float("nan"), "x", [1.0, 2.0], b"\0" * 64, memoryview(bytearray(64)))


@pytest.mark.parametrize("name", ENTRY_POINTS)
def test_each_argument_of_each_entry_point_refuses_hostile_values_without_a_crash(calls, name):
    function, recorded = getattr(native.core, name), calls[name]
    fresh = [a.copy() if isinstance(a, np.ndarray) else a for a in recorded]
    first = function(*fresh)
    rng = np.random.default_rng(0)
    tried = 0
    for i in range(len(recorded)):
        for value in _hostile(recorded[i], rng):
            args = [a.copy() if isinstance(a, np.ndarray) else a for a in recorded]
            args[i] = value
            try:
                function(*args)
            except (TypeError, ValueError, OverflowError):
                pass
            tried += 1
    assert tried > 20 * len(recorded) // 2
    again = [a.copy() if isinstance(a, np.ndarray) else a for a in recorded]
    assert function(*again) == first
