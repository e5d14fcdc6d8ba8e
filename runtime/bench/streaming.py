"""Streaming benchmark (`dimenet bench --stream N`): throughput and memory of `dimenet rectify
--points` on an N-frame points CSV.

The CSV (``models_spec/points-csv.md``) tiles the frames of a dataset, all their valid points
to 1e-4 px and 1e-4 mm (frame k is frame k mod F, id ``f<k>``, t_ns at 30 frames/s). It is then
streamed through the same path as the command, ``formats.points.read_points``,
``evaluation.rectify_points.rectified_records`` (``Rectifier.rectify`` frame by frame) and ``json_lines``, each line
written and flushed to /dev/null; then again through ``Rectifier.stream`` (``--temporal``), with a 200 Hz
gyroscope (``--temporal --motion``) and with 200 Hz lens-shift samples: their extra microseconds per frame.
Memory: the process's peak resident set size (``resource.getrusage``) after 10 % of the frames and at the end; equal
figures show the stream runs in constant memory.
"""

from __future__ import annotations

import os
import resource
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from dimenet.runtime.evaluation.rectify_points import rectified_records, streamed_records
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.points import POINTS_COLUMNS, PointsFrame, read_points
from dimenet.runtime.formats.rectified_points import counted, json_lines, run_record
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera

FRAME_NS = 33_333_333  # t_ns step: 30 frames/s
GYRO_HZ = 200.0  # the --motion pass's gyroscope rate
CSV_HEADER = ",".join(POINTS_COLUMNS) + "\n"


def points_csv(frames: Dataset, n_frames: int) -> Iterator[str]:
    """The text of a points CSV of ``n_frames`` frames tiled from ``frames`` (their valid points), a
    frame at a time after the header."""
    bodies = []
    for b in range(frames.n_frames):
        v = frames.valid[b]
        rows = np.concatenate([frames.points_2d[b][v], frames.points_3d[b][v]], axis=1)
        bodies.append([",".join(f"{c:.4f}" for c in row) + "\n" for row in rows.tolist()])
    yield CSV_HEADER
    for k in range(n_frames):
        prefix = f"f{k},{k * FRAME_NS},"
        yield "".join(prefix + row for row in bodies[k % len(bodies)])


def write_points_csv(path: str | Path, frames: Dataset, n_frames: int) -> int:
    """Write ``points_csv(frames, n_frames)`` to ``path``; returns the file's size in bytes."""
    with open(path, "w", encoding="utf-8", newline="") as f:
        f.writelines(points_csv(frames, n_frames))
    return os.path.getsize(path)


def peak_rss_mb() -> float:
    """This process's peak resident set size so far, MB (getrusage: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1e6 if sys.platform == "darwin" else peak * 1024 / 1e6


def _probed(frames: Iterable[PointsFrame], at: int, figures: dict) -> Iterator[PointsFrame]:
    """The frames, recording the peak RSS (MB) once ``at`` frames have been read."""
    for k, frame in enumerate(frames, 1):
        if k == at:
            figures["peak_rss_mb_at_10_percent"] = peak_rss_mb()
        yield frame


def run_stream_bench(folder: str | Path, n_frames: int, frames: Dataset, camera: Camera) -> dict:
    """Write an ``n_frames`` points CSV of ``frames`` into ``folder``, stream it through the bundled
    default model serving ``camera`` and return the figures (times in s, sizes in bytes, MB)."""
    path = Path(folder) / "stream.csv"
    start = time.perf_counter()
    size = write_points_csv(path, frames, n_frames)
    figures = {"frames": n_frames, "file_bytes": size, "write_s": time.perf_counter() - start}
    rectifier = Rectifier(load_model(), "dimenet", camera)
    header = run_record(rectifier, refine=False, points=str(path), camera=None)
    figures["peak_rss_mb_before"] = peak_rss_mb()
    counts: Counter = Counter()
    stream = _probed(read_points(path), max(1, n_frames // 10), figures)
    start = time.perf_counter()
    with open(os.devnull, "w", encoding="utf-8") as out:
        for line in json_lines(header, counted(rectified_records(rectifier, stream, refine=False), counts)):
            out.write(line)
            out.flush()
    seconds = time.perf_counter() - start
    passes = (
        ("temporal", {}),
        ("temporal_motion", {"motion": bench_gyro(n_frames)}),
        ("temporal_lens_shift", {"lens_shift": bench_lens_shift(n_frames)}),
    )
    for name, options in passes:
        figures[f"{name}_s"] = _timed_temporal(rectifier, path, options)
        figures[f"{name}_extra_us_per_frame"] = (figures[f"{name}_s"] - seconds) / n_frames * 1e6
    figures.update(
        refused=counts["refused"],
        fallbacks=counts["fallbacks"],
        stream_s=seconds,
        frames_per_s=n_frames / seconds,
        mb_per_s=size / 1e6 / seconds,
        peak_rss_mb=peak_rss_mb(),
        model=rectifier.model.source,
        model_sha256=rectifier.model.sha256,
    )
    return figures


def bench_gyro(n_frames: int, rate_hz: float = GYRO_HZ) -> np.ndarray:
    """(G, 4) gyroscope samples (t_ns, gx, gy, gz rad/s) at ``rate_hz`` over the bench's ``n_frames`` frames: a
    slow sway, so the OIS loop's bank has work to do."""
    t_ns = np.arange(0, n_frames * FRAME_NS + 1, int(1e9 / rate_hz), dtype=np.int64)
    t_s = t_ns * 1e-9
    rates = 0.02 * np.stack([np.sin(2.1 * t_s), np.cos(1.3 * t_s), 0.5 * np.sin(0.7 * t_s)], 1)
    return np.column_stack([t_ns, rates])


def bench_lens_shift(n_frames: int, rate_hz: float = GYRO_HZ) -> np.ndarray:
    """(G, 3) lens-shift samples (t_ns, x_shift_px, y_shift_px) at ``rate_hz`` over the bench's ``n_frames`` frames:
    a slow sway of a few px."""
    t_ns = np.arange(0, n_frames * FRAME_NS + 1, int(1e9 / rate_hz), dtype=np.int64)
    t_s = t_ns * 1e-9
    return np.column_stack([t_ns, 8.0 * np.sin(2.1 * t_s), 6.0 * np.cos(1.3 * t_s)])


def _timed_temporal(rectifier: Rectifier, path: Path, options: dict) -> float:
    """Seconds to stream the points CSV through ``Rectifier.stream(**options)`` (``--temporal``; with motion or
    lens_shift: --motion), each line written and flushed to /dev/null."""
    header = run_record(rectifier, refine=False, points=str(path), camera=None)
    records = streamed_records(rectifier.stream(**options), read_points(path))
    start = time.perf_counter()
    with open(os.devnull, "w", encoding="utf-8") as out:
        for line in json_lines(header, records):
            out.write(line)
            out.flush()
    return time.perf_counter() - start


def format_stream_report(r: dict) -> str:
    """A human-readable summary of ``run_stream_bench``'s figures."""
    return "\n".join(
        [
            f"{r['frames']} frames, {r['file_bytes'] / 1e6:.1f} MB of points CSV (written in {r['write_s']:.1f} s); "
            f"model {r['model']} (sha256 {r['model_sha256'][:16]})",
            f"rectify --points: {r['stream_s']:.1f} s, {r['frames_per_s']:.0f} frames/s, {r['mb_per_s']:.1f} MB/s; "
            f"{r['refused']} refused, {r['fallbacks']} fallbacks",
            f"--temporal: {r['temporal_s']:.1f} s, {r['temporal_extra_us_per_frame']:+.0f} us a frame over per frame; "
            f"--temporal --motion gyro: {r['temporal_motion_s']:.1f} s, "
            f"{r['temporal_motion_extra_us_per_frame']:+.0f} us; --temporal --motion lens shift: "
            f"{r['temporal_lens_shift_s']:.1f} s, {r['temporal_lens_shift_extra_us_per_frame']:+.0f} us",
            f"peak RSS {r['peak_rss_mb_before']:.1f} MB before the stream, {r['peak_rss_mb_at_10_percent']:.1f} MB "
            f"after 10 % of it, {r['peak_rss_mb']:.1f} MB at its end",
        ]
    )
