"""Streams scored (issue 51): a simulated recording (``sim.recording``) through the methods side by side, rho
(``metrics.reduction_ratio``) over its settled frames on the points the methods never see.

Methods: ``fixed`` K_c (rho 0 by construction), ``platform`` (the SDK's K alone, where the recording has one: rho
only), ``platform_temporal`` (where it has one: ``Rectifier.stream()`` fed each frame's SDK K as its K_c, which a
refused frame keeps), ``platform_prior`` (its per-frame results: ``Rectifier.rectify`` about the SDK's K),
``per_frame`` (``Rectifier.rectify``), ``temporal`` (``Rectifier.stream()``), ``gyro``
(``Rectifier.stream(motion=...)``) and ``lens_shift`` (``Rectifier.stream(lens_shift=...)``, the platform's OIS
samples). A frame is settled from SETTLE frames after
the start and after each cut or refocus; ``after_event`` is rho over frames 5 to 9 after them. e(K) is the mean
reprojection error over the frame's held-out points (``valid & ~infer_mask``: the board and the features an app
does not stream), pose by PnP under K (``metrics.reprojection_error_under_k``); e* is K_true's. A frame the
rectifier refuses keeps K_c in every method. ``coverage``: the share of frames whose K_true lies within the method's
1 sigma in every parameter; ``within_2_sigma``: the share whose |K - K_c| is within 2 sigma (what OIS off must keep).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.evaluation.metrics import reduction_ratio, reprojection_error_under_k
from dimenet.runtime.geometry import k_params
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.sim.recording import Recording, nominal_camera

SETTLE = 10  # frames after the start, a cut or a refocus before a frame counts as settled
AFTER_EVENT = (5, 10)  # frames [5, 10) after a cut or refocus: the recovery window
METHODS = ("per_frame", "temporal", "gyro", "lens_shift")


@dataclass(frozen=True)
class StreamScores:
    """One recording's figures per method (METHODS): rho over settled frames and over the recovery window (None:
    undefined, ``reduction_ratio``), coverage and within_2_sigma (shares of frames), the share of frames whose K is
    the method's own (not K_c kept), and the frames; ``tracks``: method -> (k (F, 4) px (fx, fy, cx, cy) per
    frame, sigma (F, 4) px, NaN where the method gives none)."""

    rho: dict
    rho_after_event: dict
    coverage: dict
    within_2_sigma: dict
    own_k: dict
    frames: int
    settled: int
    tracks: dict


def _masks(recording: Recording) -> tuple[np.ndarray, np.ndarray]:
    F = recording.dataset.n_frames
    settled, after = np.ones(F, bool), np.zeros(F, bool)
    for event in (0, *recording.cuts, *recording.refocus):
        settled[event : event + SETTLE] = False
        if event:
            after[event + AFTER_EVENT[0] : event + AFTER_EVENT[1]] = True
    return settled, after


def _rho(e_c, e, e_star, mask) -> Optional[float]:
    return (
        reduction_ratio(float(e_c[mask].mean()), float(e[mask].mean()), float(e_star[mask].mean()))
        if mask.any()
        else None
    )


def score_recording(recording: Recording, rectifier: Optional[Rectifier] = None) -> StreamScores:
    """Run the methods over ``recording`` (the bundled default model serving its nominal camera unless
    ``rectifier``) and score them (see the module doc)."""
    ds = recording.dataset
    if rectifier is None:
        camera = nominal_camera(recording)
        rectifier = Rectifier.load(K_c=camera.K, image_size=camera.image_size)
    streams = {
        "temporal": rectifier.stream(),
        "gyro": rectifier.stream(motion=recording.gyro),
        "lens_shift": rectifier.stream(lens_shift=recording.lens_shift),
    }
    platform_stream = rectifier.stream()
    methods = METHODS if ds.K_platform is None else (*METHODS, "platform_prior", "platform_temporal")
    K = {m: np.empty((ds.n_frames, 3, 3)) for m in methods}
    sigma = {m: np.full((ds.n_frames, 4), np.nan) for m in methods}
    own = {m: np.zeros(ds.n_frames, bool) for m in methods}
    for i in range(ds.n_frames):
        m = ds.infer_mask[i]
        p2, p3, t = ds.points_2d[i, m], ds.points_3d[i, m], int(recording.t_ns[i])
        outs = {}
        if ds.K_platform is not None:
            try:  # the stream about the SDK's K: its per-frame result is rectify about it
                out = platform_stream.update(p2, p3, t, K_c=ds.K_platform[i])
                outs.update(platform_prior=out.per_frame, platform_temporal=out.result)
            except InputError:  # the app keeps the platform's K
                for name in ("platform_prior", "platform_temporal"):
                    K[name][i] = ds.K_platform[i]
        try:
            results = {name: s.update(p2, p3, t) for name, s in streams.items()}
            outs.update(per_frame=results["temporal"].per_frame, **{n: r.result for n, r in results.items()})
        except InputError:  # a frame the rectifier refuses: the app keeps K_c (no sigma)
            for name in METHODS:
                K[name][i] = rectifier.K_c
        for name, res in outs.items():
            K[name][i] = res.K
            own[name][i] = res.fallback is None
            if res.K_cov is not None:
                sigma[name][i] = np.sqrt(np.diag(res.K_cov))
    held = ds.valid & ~ds.infer_mask
    e_c = reprojection_error_under_k(ds.points_2d, ds.points_3d, held, rectifier.K_c)
    e_star = reprojection_error_under_k(ds.points_2d, ds.points_3d, held, ds.K_true)
    settled, after = _masks(recording)
    k_true, k_c = k_params(ds.K_true), k_params(rectifier.K_c)
    rho, rho_after, coverage, within = {}, {}, {}, {}
    if ds.K_platform is not None:  # the platform's K alone
        e = reprojection_error_under_k(ds.points_2d, ds.points_3d, held, ds.K_platform)
        rho["platform"], rho_after["platform"] = _rho(e_c, e, e_star, settled), _rho(e_c, e, e_star, after)
    for name in methods:
        e = reprojection_error_under_k(ds.points_2d, ds.points_3d, held, K[name])
        rho[name], rho_after[name] = _rho(e_c, e, e_star, settled), _rho(e_c, e, e_star, after)
        k = k_params(K[name])
        with np.errstate(invalid="ignore"):
            coverage[name] = float(np.mean(np.all(np.abs(k - k_true) <= sigma[name], 1)))
            moved = np.any(k != k_c, 1)
            within[name] = float(np.mean(~moved | np.all(np.abs(k - k_c) <= 2.0 * sigma[name], 1)))
    shares = {name: float(own[name].mean()) for name in methods}
    tracks = {name: (k_params(K[name]), sigma[name]) for name in methods}
    return StreamScores(rho, rho_after, coverage, within, shares, ds.n_frames, int(settled.sum()), tracks)
