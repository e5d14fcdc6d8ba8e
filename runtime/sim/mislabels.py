"""Gross mislabels among natural labels (issue 50, models_spec/simulator.md, "Mislabels"): real hand labels and
detections carry a few points clicked on the wrong feature, tens of pixels off, beside their Gaussian noise.

A share of a natural frame's labelled points, drawn point by point, is moved by MISLABEL_PX (uniform) in a
uniform direction; a move that would leave the image is turned back (the other way), and a point neither way keeps
its label, so every label stays inside the image as a labeller's click does. The draws come from a generator of
their own (``mislabel_rng``), so a dataset with mislabels differs from the same seed's without only in the moved
points.
"""

from __future__ import annotations

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.rectify.checks import ImageBounds

MISLABEL_PX = (10.0, 50.0)  # the size of a gross mislabel, px
MAX_MISLABEL_SHARE = 0.5  # beyond, the labels are not a labelling
_STREAM = 0x6D69736C  # "misl": the generator's key beside the dataset's seed


def checked_share(share: float) -> float:
    """A mislabel share in [0, MAX_MISLABEL_SHARE], or InputError."""
    number = isinstance(share, (int, float, np.floating)) and not isinstance(share, bool)
    if not number or not 0 <= share <= MAX_MISLABEL_SHARE:
        raise InputError(f"the mislabel share must be a number in [0, {MAX_MISLABEL_SHARE}], got {share!r}")
    return float(share)


def mislabel_rng(seed: int) -> np.random.Generator:
    """The mislabels' own generator for the dataset of ``seed``."""
    return np.random.default_rng([int(seed), _STREAM])


def mislabelled(
    points_2d_px: np.ndarray, labelled: np.ndarray, share: float, image_size_px, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 2) px with the mislabels moved, moved (N,) bool) of one frame's points (N, 2) px, of which the
    ``labelled`` (N,) bool ones may be mislabelled, each with probability ``share``, in the image of
    ``image_size_px`` (width, height) px."""
    n = len(points_2d_px)
    draw = rng.random(n) < share
    radius = rng.uniform(*MISLABEL_PX, n)
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    offset = radius[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)
    image = ImageBounds(image_size_px)
    out = points_2d_px.copy()
    moved = np.zeros(n, bool)
    for i in np.flatnonzero(draw & labelled):
        for step in (offset[i], -offset[i]):
            to = points_2d_px[i] + step
            if np.all(to >= image.low) and np.all(to <= image.high):
                out[i], moved[i] = to, True
                break
    return out, moved
