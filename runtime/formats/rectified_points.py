"""The JSON lines of a points file's rectification (`dimenet rectify --points`; models_spec/points-csv.md):
``run_record`` (the camera, model and mode of the run: the first line, ``format`` FORMAT), then one
``frame_record`` or ``error_record`` per frame of ``formats.points``; ``json_lines`` writes them and
``counted`` tallies them. The rectifier runs over the frames in ``evaluation.rectify_points``.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterable, Iterator
from itertools import chain, islice
from typing import Optional

import numpy as np

from dimenet.runtime import __version__
from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.points import PointsFrame
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.results import Rectification

FORMAT = "dimenet-rectified-points/1"  # the output's first line: {"format": FORMAT, ...}


def run_record(rectifier: Rectifier, *, refine: bool, points: str, camera: Optional[str]) -> dict:
    """The first output line: which camera (K_c (3, 3) px, image_size (width, height) px,
    dist_coeffs or None) and model (source, sha256) rectified the points file, in which mode."""
    dist = rectifier.dist_coeffs
    return {
        "format": FORMAT,
        "dimenet_version": __version__,
        "points": points,
        "camera": camera,
        "model": rectifier.model.source,
        "model_sha256": rectifier.model.sha256,
        "mode": rectifier.mode,
        "refine": refine,
        "K_c": rectifier.K_c.tolist(),
        "image_size": [int(v) for v in rectifier.image_size],
        "dist_coeffs": None if dist is None else dist.tolist(),
    }


def frame_record(frame: PointsFrame, res: Rectification) -> dict:
    """One rectified frame: K (3, 3) px, rvec rad and tvec mm {W}->{C}, e and e_c px, fallback and its
    fallback_code (``FALLBACK_CODES``), K_sigma_px the standard deviations of (fx, fy, cx, cy) px or None (no
    uncertainty model, or K_c); and K_c (3, 3) px when the frame gave its own (points format 2)."""
    cov = res.K_cov
    own = {} if frame.K_c is None else {"K_c": frame.K_c.tolist()}
    return {
        "frame_id": frame.frame_id,
        "t_ns": frame.t_ns,
        "K": res.K.tolist(),
        "rvec": res.rvec.tolist(),
        "tvec": res.tvec.tolist(),
        "e_px": float(res.reprojection_error_px),
        "e_c_px": float(res.reprojection_error_kc_px),
        "fallback": res.fallback,
        "fallback_code": res.fallback_code,
        "K_sigma_px": None if cov is None else np.sqrt(np.diag(cov)).tolist(),
        **own,
    }


def error_record(frame: PointsFrame, exc: InputError) -> dict:
    """A frame the rectifier refused: why, and no K."""
    return {"frame_id": frame.frame_id, "t_ns": frame.t_ns, "error": str(exc)}


def json_lines(header: dict, records: Iterable[dict]) -> Iterator[str]:
    """The output's lines (JSON, each ending in a newline): ``header`` (the ``run_record``), then
    the records. The header waits for the first record, so a points file that cannot be read
    (the error comes before any frame) leaves no output."""
    records = iter(records)
    first = list(islice(records, 1))
    for record in chain([header], first, records):
        yield json.dumps(record, allow_nan=False) + "\n"


def counted(records: Iterable[dict], counts: Counter) -> Iterator[dict]:
    """The records, counting into ``counts`` the frames, those refused and the fallbacks."""
    for record in records:
        counts["frames"] += 1
        counts["refused"] += "error" in record
        counts["fallbacks"] += record.get("fallback") is not None
        yield record
