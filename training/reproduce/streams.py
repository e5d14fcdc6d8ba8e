"""Streams beside the paper's tables (issue 51): simulated hand-held recordings of the held-out trace model
(``sim.recording``) through every stream method (``runtime.bench.streams``), the bundled default model serving each
recording's nominal camera; rho over settled frames on the points no method sees, and one natural recording's K
over time for the plot (``report.plot_stream``)."""

from __future__ import annotations

import numpy as np

from dimenet.runtime.bench.streams import score_recording
from dimenet.runtime.geometry import k_params
from dimenet.runtime.sim.recording import nominal_camera, simulate_recording

SECONDS = 6.0
QUICK_SECONDS = 1.5  # `reproduce --quick`: a smoke run
RECORDINGS = (("natural", 0), ("natural", 1), ("natural", 2), ("rig", 0), ("rig", 1))
PLOTTED = ("natural", 0)


def _plain(a: np.ndarray) -> list:
    """A float array as JSON's lists, NaN as None."""
    return np.where(np.isnan(a), None, np.round(a, 4)).tolist()


def run_streams(seconds: float = SECONDS) -> dict:
    """{"rho": "<kind> <seed>" -> method -> rho over settled frames (None: undefined), "plot": the PLOTTED
    recording's t_s, k_true, k_c, k_platform (fx, fy, cx, cy px per frame) and per method k and sigma px}."""
    rho, plot = {}, None
    for kind, seed in RECORDINGS:
        recording = simulate_recording(seed, seconds=seconds, kind=kind, held_out=True)
        scores = score_recording(recording)
        rho[f"{kind} {seed}"] = scores.rho
        if (kind, seed) == PLOTTED:
            ds = recording.dataset
            plot = {
                "name": f"{kind} {seed}",
                "t_s": ((recording.t_ns - recording.t_ns[0]) * 1e-9).tolist(),
                "k_true": _plain(k_params(ds.K_true)),
                "k_c": k_params(nominal_camera(recording).K).tolist(),
                "k_platform": _plain(k_params(ds.K_platform)),
                "methods": {m: {"k": _plain(k), "sigma": _plain(sd)} for m, (k, sd) in scores.tracks.items()},
            }
    return {"rho": rho, "plot": plot}
