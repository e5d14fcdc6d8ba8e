"""Which implementation runs (dimenet.runtime.native): chosen once from DIMENET_IMPLEMENTATION, switched
in process only by ``set_implementation``; the rectifier's hot path and ``grid_features`` take the
compiled core when it runs; `dimenet --version` and `dimenet bench` say which; the binding refuses
arrays of the wrong kind and is safe to call from several threads at once."""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import native
from dimenet.runtime.bench.latency import format_report, run_bench
from dimenet.runtime.rectify import stages
from dimenet.runtime.rectify.features import FeatureSpec, grid_features
from dimenet.runtime.rectify.rectifier import Rectifier

compiled = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")
IMAGE = (4032, 3024)


def _chosen(value):
    env = {k: v for k, v in os.environ.items() if k != native.ENV_VARIABLE}
    if value is not None:
        env[native.ENV_VARIABLE] = value
    code = "from dimenet.runtime import native; print(native.implementation())"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)


def test_the_environment_chooses_the_implementation_once():
    built = "c" if native.compiled_available() else "python"
    assert _chosen(None).stdout.strip() == built
    assert _chosen("").stdout.strip() == built
    assert _chosen("python").stdout.strip() == "python"
    asked_c = _chosen("c")
    if native.compiled_available():
        assert asked_c.stdout.strip() == "c"
    else:
        assert asked_c.returncode != 0 and "the compiled core is not built" in asked_c.stderr
    bad = _chosen("fast")
    assert bad.returncode != 0 and "DIMENET_IMPLEMENTATION must be one of c, python" in bad.stderr


def test_the_command_line_says_which_implementation_runs_and_refuses_an_unknown_one():
    env = dict(os.environ, **{native.ENV_VARIABLE: "python"})
    run = [sys.executable, "-m", "dimenet", "--version"]
    shown = subprocess.run(run, capture_output=True, text=True, env=env, timeout=60)
    assert shown.returncode == 0 and shown.stdout.strip().endswith("(implementation python)")
    env[native.ENV_VARIABLE] = "C"
    bad = subprocess.run(run, capture_output=True, text=True, env=env, timeout=60)
    assert bad.returncode == 2 and bad.stderr.startswith("dimenet: error: DIMENET_IMPLEMENTATION must be one of")


def test_set_implementation_switches_in_process_and_using_restores_it():
    before = native.implementation()
    with native.using("python"):
        assert native.implementation() == "python" and native.core is None
    assert native.implementation() == before
    with pytest.raises(native.ImplementationError, match="must be one of c, python"):
        native.set_implementation("numpy")
    assert native.implementation() == before


def test_the_bench_reports_the_implementation():
    with native.using("python"):
        report = run_bench(frames=3, points=60)
    assert report["implementation"] == "python"
    assert "implementation python" in format_report(report)


class _Counting:
    """native.core with its calls counted."""

    def __init__(self, core):
        self.core, self.calls = core, []

    def __getattr__(self, name):
        function = getattr(self.core, name)

        def counted(*args):
            self.calls.append(name)
            return function(*args)

        return counted


@compiled
def test_the_hot_path_and_grid_features_run_the_compiled_core(monkeypatch):
    with native.using("c"):
        spy = _Counting(native.core)
        monkeypatch.setattr(native, "core", spy)
        rect = Rectifier.load(K_c=K_TEST, image_size=IMAGE)
        x, X, _, rvec, tvec = random_frames(np.random.default_rng(1), frames=2, points=60, noise_px=0.5)
        rect.rectify(x[0], X[0])
        grid_features(x, X, None, K_TEST, IMAGE, FeatureSpec(), poses=(rvec, tvec))
        # validation's fast tests, the PnP's unit, the feature, then the pose steps and the check stage's e(K)
        # (and SQPnP's unit again where a rule refuses K at the steps' pose)
        assert spy.calls[:3] == ["frame_checks", "power_of_two_unit", "frame_features"]
        assert spy.calls[-1] == "grid_features"
        assert set(spy.calls[3:-1]) <= {"pose_steps", "power_of_two_unit"}


@compiled
def test_the_binding_refuses_arrays_of_the_wrong_kind():
    spec = FeatureSpec(data_step=True, moments=True)
    x, X, _, rvec, tvec = random_frames(np.random.default_rng(2), frames=1, points=30)
    p2, p3, r, t = x[0], X[0], rvec[0], tvec[0]
    feats = np.empty((1, spec.size))
    core = native._compiled()[0]
    ok = (p2, p3, r, t, K_TEST, IMAGE, spec.native_layout, feats)
    assert isinstance(core.frame_features(*ok), float)
    wrong = {
        0: p2.astype(np.float32),  # another type
        1: np.asfortranarray(np.tile(p3, (1, 2)))[:, :3],  # not contiguous
        2: np.zeros(4),  # another shape
        7: np.empty((1, spec.size - 1)),  # the wrong feature size
    }
    for i, value in wrong.items():
        args = list(ok)
        args[i] = value
        with pytest.raises((TypeError, ValueError)):
            core.frame_features(*args)
    with pytest.raises(TypeError):
        core.frame_features(*ok[:7])
    frozen = feats.copy()
    frozen.setflags(write=False)
    with pytest.raises(TypeError, match="writable"):
        core.frame_features(*ok[:7], frozen)


@compiled
def test_threads_calling_the_compiled_core_at_once_get_the_serial_results():
    """The kernel runs without the GIL and keeps no state: eight threads give what one does, bit for bit."""
    rng = np.random.default_rng(7)
    x, X, _, rvec, tvec = random_frames(rng, frames=64, points=200, noise_px=1.0)
    spec = FeatureSpec(data_step=True, moments=True, depth_mm=500.0)
    cam = Rectifier.load(K_c=K_TEST, image_size=IMAGE)._cam

    def frame(b):
        return stages.frame_features(cam, x[b], X[b], rvec[b], tvec[b])[0]

    def batch(b):
        return grid_features(
            x[b : b + 8], X[b : b + 8], None, K_TEST, IMAGE, spec, poses=(rvec[b : b + 8], tvec[b : b + 8])
        )

    with native.using("c"):
        serial = [frame(b) for b in range(64)], [batch(b) for b in range(0, 64, 8)]
        with ThreadPoolExecutor(8) as pool:
            threaded = list(pool.map(frame, range(64))), list(pool.map(batch, range(0, 64, 8)))
    for one, other in zip(serial, threaded):
        for a, b in zip(one, other):
            np.testing.assert_array_equal(a, b)


@compiled
def test_the_hot_path_takes_arrays_of_another_type_or_layout_as_numpy_does():
    rng = np.random.default_rng(4)
    x, X, _, rvec, tvec = random_frames(rng, frames=1, points=50, noise_px=0.5)
    cam = Rectifier.load(K_c=K_TEST, image_size=IMAGE)._cam
    with native.using("python"):
        want = stages.frame_features(cam, x[0], X[0], rvec[0], tvec[0])
    with native.using("c"):
        odd = np.asfortranarray(x[0]), X[0].tolist(), list(rvec[0]), np.repeat(tvec[0], 2)[::2]  # strided
        got = stages.frame_features(cam, *odd)
    np.testing.assert_array_equal(got[0], want[0])
    assert got[1] == want[1]
