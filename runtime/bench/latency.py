"""Latency benchmark of the runtime (`dimenet bench`): ``Rectifier.rectify`` against OpenCV's
iterative PnP under K_c, on the same simulated points, in the same run.

Frames: one ``simulate(BENCH_PROFILE, seed)`` dataset; each benchmark frame is one of its
frames with at least ``points`` valid points (drawn with replacement) and a random subset of
exactly ``points`` of them. Times are wall-clock microseconds per call (time.perf_counter_ns);
the baseline, then ``rectify``, then (with ``batch`` > 1) ``rectify_batch`` each run over all
frames in their own loop, after one untimed warm-up call of ``rectify``; with ``callers`` > 1, that many
Python threads then share the one Rectifier, each calling ``rectify`` on its share of the frames, and
their frames/s over the one-by-one loop's is ``callers_speedup``.
"""

from __future__ import annotations

import platform
import threading
import time
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import onnxruntime as ort

from dimenet.runtime.errors import InputError, ModelError
from dimenet.runtime.evaluation.calibration import dataset_camera
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.native import implementation
from dimenet.runtime.rectify.model import OnnxModel, load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.simulator import simulate

BENCH_PROFILE = "galaxy-s8"


def percentiles_us(samples_us) -> dict:
    """p50, p90, p99 and max (µs) of a list of durations in µs."""
    a = np.asarray(samples_us, dtype=np.float64)
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {"p50": float(p50), "p90": float(p90), "p99": float(p99), "max": float(a.max())}


def bench_frames(n_frames: int, n_points: int, image_size, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n_frames, n_points, 2) px and (n_frames, n_points, 3) mm correspondences from simulated frames."""
    profile = get_profile(BENCH_PROFILE)
    if tuple(image_size) != tuple(profile.image_size_px):
        raise ModelError(
            f"the bench simulates {BENCH_PROFILE} frames of {profile.image_size_px[0]}x"
            f"{profile.image_size_px[1]} px; the model serves {image_size[0]}x{image_size[1]} px"
        )
    ds = simulate(profile, seed=seed)
    counts = ds.valid.sum(1)
    usable = np.flatnonzero(counts >= n_points)
    if n_frames < 1 or n_points < 6 or len(usable) == 0:
        raise InputError(
            f"--frames must be >= 1 and --points between 6 and {int(counts.max())} "
            f"(the simulated frames' points), got {n_frames} and {n_points}"
        )
    rng = np.random.default_rng(seed)
    picks = rng.choice(usable, n_frames)
    idx = [np.sort(rng.choice(np.flatnonzero(ds.valid[b]), n_points, replace=False)) for b in picks]
    p2 = np.stack([ds.points_2d[b][i] for b, i in zip(picks, idx)])
    p3 = np.stack([ds.points_3d[b][i] for b, i in zip(picks, idx)])
    return p2, p3


def bench_rectifier(model: OnnxModel, mode: str, frames: Optional[Dataset] = None) -> Rectifier:
    """``model`` serving the bench's simulated phone: a device model its own camera, a generic one
    the phone's camera as a user would know it, K_c calibrated on the train split of ``frames``
    (default: the bench profile's seed-0 set)."""
    if model.spec.generic is None:
        return Rectifier(model, mode)
    frames = simulate(get_profile(BENCH_PROFILE), seed=0) if frames is None else frames
    return Rectifier(model, mode, dataset_camera(frames))


def cpu_model() -> str:
    """The CPU's marketing name (Linux /proc/cpuinfo), else what platform knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _single_calls(rectifier: Rectifier, p2, p3, refine: bool) -> tuple[list, dict, int]:
    """End-to-end durations (µs) of ``rectify`` per frame, its stage durations, the fallback count."""
    end_to_end, stages, fallbacks = [], {}, 0
    clock = time.perf_counter_ns
    for x, X in zip(p2, p3):
        start = clock()
        res = rectifier.rectify(x, X, refine=refine)
        end_to_end.append((clock() - start) / 1e3)
        for name, us in res.timings_us.items():
            stages.setdefault(name, []).append(us)
        fallbacks += res.fallback is not None
    return end_to_end, stages, fallbacks


def _baseline_calls(K_c: np.ndarray, p2, p3) -> list:
    """Durations (µs) of cv2.solvePnP ITERATIVE under K_c per frame."""
    durations = []
    clock = time.perf_counter_ns
    for x, X in zip(p2, p3):
        start = clock()
        cv2.solvePnP(X, x, K_c, None, flags=cv2.SOLVEPNP_ITERATIVE)
        durations.append((clock() - start) / 1e3)
    return durations


def _batch_rate(rectifier: Rectifier, p2, p3, batch: int, refine: bool) -> float:
    """Frames per second through ``rectify_batch`` in chunks of ``batch`` frames."""
    valid = np.ones(p2.shape[:2], bool)
    start = time.perf_counter_ns()
    for i in range(0, len(p2), batch):
        rectifier.rectify_batch(p2[i : i + batch], p3[i : i + batch], valid[i : i + batch], refine=refine)
    return len(p2) / ((time.perf_counter_ns() - start) / 1e9)


def _callers_rate(rectifier: Rectifier, p2, p3, callers: int, refine: bool) -> float:
    """Frames per second of ``callers`` Python threads calling ``rectify`` on one shared Rectifier, the
    frames dealt out in turn (thread j takes frames j, j + callers, ...), from the first start to the last
    end."""

    def work(j: int) -> None:
        for i in range(j, len(p2), callers):
            rectifier.rectify(p2[i], p3[i], refine=refine)

    threads = [threading.Thread(target=work, args=(j,)) for j in range(callers)]
    start = time.perf_counter_ns()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return len(p2) / ((time.perf_counter_ns() - start) / 1e9)


def run_bench(
    model: Optional[str] = None,
    *,
    frames: int = 2000,
    points: int = 320,
    threads: int = 1,
    batch: int = 1,
    callers: int = 1,
    refine: bool = False,
    seed: int = 0,
    mode: str = "dimenet",
) -> dict:
    """Benchmark a model (default: the bundled one) and return the report as a JSON-able dict."""
    for name, value in (("threads", threads), ("batch", batch), ("callers", callers)):
        if value < 1:
            raise InputError(f"--{name} must be >= 1, got {value}")
    cv2.setNumThreads(threads)
    start = time.perf_counter_ns()
    onnx_model = load_model(model, threads=threads)
    session_ms = (time.perf_counter_ns() - start) / 1e6
    rectifier = bench_rectifier(onnx_model, mode)
    p2, p3 = bench_frames(frames, points, rectifier.image_size, seed=seed)
    start = time.perf_counter_ns()
    rectifier.rectify(p2[0], p3[0], refine=refine)
    first_call_us = (time.perf_counter_ns() - start) / 1e3
    baseline = _baseline_calls(rectifier.K_c, p2, p3)
    end_to_end, stages, fallbacks = _single_calls(rectifier, p2, p3, refine)
    report = {
        "frames": frames,
        "points": points,
        "threads": threads,
        "refine": refine,
        "batch": batch,
        "mode": mode,
        "end_to_end_us": percentiles_us(end_to_end),
        "baseline_solvepnp_us": percentiles_us(baseline),
        "ratio_p50": float(np.median(end_to_end) / np.median(baseline)),
        "stages_us": {name: percentiles_us(v) for name, v in stages.items()},
        "single_frames_per_s": float(len(end_to_end) / (np.sum(end_to_end) / 1e6)),
        "fallbacks": fallbacks,
        "session_create_ms": session_ms,
        "first_call_us": first_call_us,
        "ort_version": ort.__version__,
        "providers": rectifier.model.providers,
        "opencv_version": cv2.__version__,
        "numpy_version": np.__version__,
        "implementation": implementation(),
        "cpu_model": cpu_model(),
        "model": rectifier.model.source,
        "model_sha256": rectifier.model.sha256,
    }
    if batch > 1:
        report["batch_frames_per_s"] = _batch_rate(rectifier, p2, p3, batch, refine)
        report["batch_speedup"] = report["batch_frames_per_s"] / report["single_frames_per_s"]
    if callers > 1:
        report["callers"] = callers
        report["callers_frames_per_s"] = _callers_rate(rectifier, p2, p3, callers, refine)
        report["callers_speedup"] = report["callers_frames_per_s"] / report["single_frames_per_s"]
    return report


def format_report(r: dict) -> str:
    """A human-readable summary of ``run_bench``'s report."""
    row = lambda name, s: f"  {name:<22} {s['p50']:9.1f} {s['p90']:9.1f} {s['p99']:9.1f} {s['max']:9.1f}"  # noqa: E731
    lines = [
        f"{r['frames']} simulated {BENCH_PROFILE} frames x {r['points']} points, {r['threads']} thread(s), "
        f"mode {r['mode']}"
        f"{', refine' if r['refine'] else ''}; model {r['model']} (sha256 {r['model_sha256'][:16]})",
        f"onnxruntime {r['ort_version']} {','.join(r['providers'])}, OpenCV {r['opencv_version']}, "
        f"CPU {r['cpu_model']}; implementation {r['implementation']}",
        f"session creation {r['session_create_ms']:.1f} ms, first call {r['first_call_us']:.0f} µs",
        f"  {'µs':<22} {'p50':>9} {'p90':>9} {'p99':>9} {'max':>9}",
        *(row(f"stage {name}", s) for name, s in r["stages_us"].items()),
        row("rectify end to end", r["end_to_end_us"]),
        row("baseline ITERATIVE K_c", r["baseline_solvepnp_us"]),
        f"ratio_p50 (rectify / baseline) {r['ratio_p50']:.2f}; {r['single_frames_per_s']:.0f} frames/s one by one; "
        f"{r['fallbacks']} fallbacks",
    ]
    if "batch_frames_per_s" in r:
        lines.append(f"batches of {r['batch']}: {r['batch_frames_per_s']:.0f} frames/s ({r['batch_speedup']:.2f}x)")
    if "callers_frames_per_s" in r:
        lines.append(
            f"{r['callers']} caller threads on one Rectifier: {r['callers_frames_per_s']:.0f} frames/s "
            f"({r['callers_speedup']:.2f}x one caller)"
        )
    return "\n".join(lines)
