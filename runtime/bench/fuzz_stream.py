"""The fuzz's streams (``Rectifier.stream()``, issue 51's surfaces): short recordings with hostile frame times,
per-frame K_c (the platform's K), gyroscope and lens-shift samples, stream options, and hostile frames among clean
ones.

Every update must end in a ``DimenetError`` (``typed``) or in a frame that is no confident wrong K (``ok``: as
``fuzz.judge_frame`` under the frame's own K_c, and where the stream's K stands, e no worse than e_c by the
never-worse rule and a finite K_cov). After the hostile frames, a clean frame must give a K where it gives one in a
fresh stream of the same options: a typed error leaves the stream usable (else ``silent-wrong``: the stream was left
broken).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from dimenet.runtime.bench.fuzz import FuzzReport, frame_variants, judge_frame, outcome_of, random_rig_frames
from dimenet.runtime.rectify.checks import loses_to_k_c
from dimenet.runtime.rectify.clock import MAX_T_NS
from dimenet.runtime.rectify.rectifier import Rectifier

FRAMES = 4  # hostile frames per case, then one clean frame
FRAME_NS = 33_333_333  # 30 frames/s
T0_NS = 10**15  # the clean stream's first frame


def _times(rng: np.random.Generator) -> Iterator[tuple[str, list]]:
    """(name, FRAMES frame times) that are hostile or odd."""
    clean = [T0_NS + i * FRAME_NS for i in range(FRAMES)]
    yield "t_ns decreasing", clean[::-1]
    yield "t_ns repeated", [T0_NS] * FRAMES
    yield "t_ns with a gap", [T0_NS, T0_NS + FRAME_NS, T0_NS + 10**10, T0_NS + 10**10 + FRAME_NS]
    yield "t_ns at the clock's ends", [-MAX_T_NS, MAX_T_NS, -MAX_T_NS, 0]
    yield "t_ns past the clock", [MAX_T_NS + 1, -(2**64), 2**70, 0]
    yield "t_ns numpy int64 ends", [np.int64(-(2**63)), np.int64(2**63 - 1), np.int64(0), np.int64(1)]
    yield "t_ns numpy uint64", [np.uint64(2**64 - 1), np.uint64(0), np.uint64(5), np.uint64(3)]
    yield "t_ns integral floats", [float(t) for t in clean]
    yield "t_ns fractional", [t + rng.uniform(0.1, 0.9) for t in clean]
    yield "t_ns not finite", [T0_NS, float("nan"), float("inf"), -float("inf")]
    yield "t_ns of other types", [True, "5", [T0_NS], {"t": 1}]
    yield "t_ns None among times", [T0_NS, None, T0_NS + 2 * FRAME_NS, None]


def _k_c(rng: np.random.Generator, K: np.ndarray) -> Iterator[tuple[str, list]]:
    """(name, FRAMES per-frame K_c) that are hostile or odd, about K (3, 3) px."""

    def moved(df, dcx, dcy):
        k = K.copy()
        k[0, 0] *= 1 + df
        k[1, 1] *= 1 + df
        k[:2, 2] += (dcx, dcy)
        return k

    yield "K_c jittered", [moved(*rng.normal(0, (0.01, 20, 20))) for _ in range(FRAMES)]
    yield "K_c jumping", [moved(0.3 * (i % 2), 0, 0) for i in range(FRAMES)]
    yield "K_c far off", [moved(rng.uniform(-0.8, 3), *rng.uniform(-1500, 1500, 2)) for _ in range(FRAMES)]
    bad = K.copy()
    bad[rng.integers(2), rng.integers(3)] = rng.choice([np.nan, np.inf, -K[0, 0], 0.0, 1e300])
    yield "K_c not finite or not positive", [bad] * FRAMES
    skew = K.copy()
    skew[0, 1], skew[2, 2] = rng.uniform(1, 50), rng.uniform(0.5, 2)
    yield "K_c skewed", [skew] * FRAMES
    yield "K_c of other shapes", [np.eye(4), K[:2], K.ravel(), [[1, 2], [3]]]
    yield "K_c as lists and strings", [K.tolist(), K.astype(str), K.tolist(), None]


def _samples(rng: np.random.Generator, columns: int) -> np.ndarray:
    """Clean (G, columns) samples at 200 Hz around the clean frames: t_ns, then small rates (rad/s) or shifts (px)."""
    t = np.arange(T0_NS - 10**9, T0_NS + 2 * 10**9, 5_000_000, dtype=np.float64)
    return np.c_[t, rng.normal(0, 0.05 if columns == 4 else 20.0, (len(t), columns - 1))]


def _motions(rng: np.random.Generator) -> Iterator[tuple[str, dict]]:
    """(name, stream options) with gyroscope or lens-shift samples, or other options, that are hostile or odd."""
    for kind, columns in (("motion", 4), ("lens_shift", 3)):
        s = _samples(rng, columns)
        edited = s.copy()
        edited[rng.integers(len(s)), rng.integers(columns)] = rng.choice([np.nan, np.inf, 1e300])
        yield f"{kind} clean", {kind: s}
        yield f"{kind} with a NaN, inf or huge value", {kind: edited}
        yield f"{kind} unsorted", {kind: s[rng.permutation(len(s))]}
        yield f"{kind} of one sample", {kind: s[:1]}
        yield f"{kind} before the frames", {kind: s[:50]}
        yield f"{kind} after the frames", {kind: s[-50:]}
        yield f"{kind} on another clock", {kind: np.c_[s[:, 0] + 10.0**15, s[:, 1:]]}
        yield f"{kind} large", {kind: np.c_[s[:, 0], s[:, 1:] * 1e4]}
        yield f"{kind} of other shapes", {kind: s[:, :2] if rng.random() < 0.5 else s[None]}
        yield f"{kind} as strings", {kind: s.astype(str)}
    yield "lens_shift_scale hostile", {"lens_shift": _samples(rng, 3), "lens_shift_scale": rng.choice([0, -1, 1e9])}
    yield "both motions", {"motion": _samples(rng, 4), "lens_shift": _samples(rng, 3)}
    yield "tau_s hostile", {"tau_s": rng.choice([(0, 1, 1, 1), (np.nan,) * 4, (np.inf,) * 4, (1e-300,) * 4])}
    yield "frame_s hostile", {"frame_s": rng.choice([0.0, -1.0, np.inf, 1e-300, 1e300])}


def judge_stream_frame(rect: Rectifier, X: np.ndarray, frame) -> tuple[str, str]:
    """A stream's frame is ok when its result is (``fuzz.judge_frame``, under the frame's K_c), and where the stream's
    K stands, it fits the frame's points no worse than K_c (``checks.loses_to_k_c``) with a finite K_cov."""
    res = frame.result
    verdict = judge_frame(rect, X, res, res.K_c)
    if verdict[0] != "ok" or not frame.fused:
        return verdict
    e, e_c = res.reprojection_error_px, res.reprojection_error_kc_px
    if loses_to_k_c(e, e_c, float(res.K_c[0, 0])):
        return "silent-wrong", f"the stream's K stands with e {e} px over e_c {e_c} px"
    if not np.all(np.isfinite(res.K_cov)):
        return "silent-wrong", f"the stream's K_cov is not finite: {res.K_cov.tolist()}"
    return "ok", ""


def _run(rect: Rectifier, case: str, x, X, options: dict, inputs: list, report: FuzzReport) -> None:
    """One stream with ``options`` through ``inputs`` ((points_2d, points_3d, t_ns, K_c) per frame), then a clean
    frame (a clean time after the last, at the Rectifier's K_c), each update's outcome added to ``report``."""
    made = []
    verdict = outcome_of(lambda: rect.stream(**options), lambda s: made.append(s) or ("ok", ""))
    if not made:
        report.add("stream", case, *verdict)
        return
    stream = made[0]
    for p2, p3, t_ns, K_c in inputs:
        kwargs = {} if K_c is None else {"K_c": K_c}
        verdict = outcome_of(
            lambda p2=p2, p3=p3, t_ns=t_ns, kwargs=kwargs: stream.update(p2, p3, t_ns, **kwargs),
            lambda r, p3=p3: judge_stream_frame(rect, p3, r),
        )
        report.add("stream", case, *verdict)
    t_ns = T0_NS + 10 * FRAME_NS
    clean = outcome_of(lambda: stream.update(x, X, t_ns), lambda r: judge_stream_frame(rect, X, r))
    fresh = outcome_of(lambda: rect.stream(**options).update(x, X, t_ns), lambda r: ("ok", ""))
    if clean[0] == "typed" and fresh[0] == "ok":
        clean = ("silent-wrong", "a clean frame refused after the hostile ones: the stream was left broken")
    report.add("stream", f"{case}, then a clean frame", *clean)


def fuzz_streams(rect: Rectifier, frames, n_cases: int, rng: np.random.Generator, report: FuzzReport) -> None:
    """``n_cases`` hostile streams made from ``frames`` (a dataset's rig frames): each FRAMES updates of one frame's
    points with 0.3 px of noise, one hostile element (times, per-frame K_c, samples, options, or one hostile frame
    among clean ones), then a clean frame."""
    done = 0
    for x, X, K in random_rig_frames(frames, rng):
        if done >= n_cases:
            break
        times = [T0_NS + i * FRAME_NS for i in range(FRAMES)]
        noisy = [x + rng.normal(0, 0.3, x.shape) for _ in range(FRAMES)]

        def clean(ts=times, kcs=(None,) * FRAMES, noisy=noisy, X=X):
            return [(p2, X, t, k) for p2, t, k in zip(noisy, ts, kcs)]

        cases = [(name, {}, clean(ts=ts)) for name, ts in _times(rng)]
        cases += [(name, {}, clean(kcs=kcs)) for name, kcs in _k_c(rng, rect.K_c)]
        cases += [(name, options, clean()) for name, options in _motions(rng)]
        for name, p2, p3 in frame_variants(rng, x, X, K):
            inputs = clean()
            inputs[FRAMES // 2] = (p2, p3, times[FRAMES // 2], None)
            cases.append((f"frame {name}", {}, inputs))
        for i in rng.permutation(len(cases)):
            if done >= n_cases:
                break
            done += 1
            name, options, inputs = cases[i]
            _run(rect, name, x, X, options, inputs, report)
