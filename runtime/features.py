"""The DIME-Net input: the gridified OIS discrepancy feature (paper Sec. IV-A).

One implementation, numpy only, used by training, evaluation, export checks and the runtime.

1. Pose {W}->{C0}: PnP under the prior K_c on the frame's inference points (SQPnP).
2. Point feature f_i = [dx, dy, X, Y, 1/Z]: dx, dy = K_c proj(X_C0) - x (px, the projection
   model discrepancy, PMD) and (X, Y, Z) the point in {C0} (mm).
3. Each cell of the u x v grid (runtime/grid.py) holds the mean of its points' features;
   empty cells are zero. Flattened cell by cell in (row, column) order, channels inside.
4. Every channel is multiplied by a fixed scale (no shift, so a zero feature stays zero).

Variants (paper Table 3): A all five channels; B PMD only; C PMD + 1/Z; D PMD + X, Y;
E X, Y, 1/Z only.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from .errors import InputError
from .geometry import k_params, rvec_to_matrix, solve_pnp_start
from .grid import Grid

CHANNELS = ("dx", "dy", "X", "Y", "inv_z")
VARIANTS = {
    "A": ("dx", "dy", "X", "Y", "inv_z"),
    "B": ("dx", "dy"),
    "C": ("dx", "dy", "inv_z"),
    "D": ("dx", "dy", "X", "Y"),
    "E": ("X", "Y", "inv_z"),
}
# Fixed per-channel scales bringing each channel to order 1 on hand-held rig data:
# PMD of ~10 px, {C0} coordinates of ~100 mm, inverse depth of ~1/500 mm^-1.
DEFAULT_SCALE = {"dx": 0.1, "dy": 0.1, "X": 0.01, "Y": 0.01, "inv_z": 500.0}


@dataclass(frozen=True)
class FeatureSpec:
    """What the network sees: grid, channel variant and per-channel scale (units: 1/px, 1/mm, mm)."""

    grid: Grid = Grid(8, 6)
    variant: str = "A"
    scale: dict = field(default_factory=lambda: dict(DEFAULT_SCALE))

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise InputError(f"feature variant must be one of {', '.join(VARIANTS)}, got {self.variant!r}")
        missing = [c for c in CHANNELS if c not in self.scale]
        if missing:
            raise InputError(f"feature scale lacks channel {missing[0]!r}")

    @property
    def channels(self) -> tuple:
        return VARIANTS[self.variant]

    @property
    def size(self) -> int:
        return len(self.channels) * self.grid.n_cells

    def to_dict(self) -> dict:
        return {"grid": str(self.grid), "variant": self.variant, "scale": dict(self.scale)}

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureSpec":
        return cls(grid=Grid.parse(d["grid"]), variant=d["variant"], scale={k: float(v) for k, v in d["scale"].items()})


def poses_c0(points_2d, points_3d, mask, K_c) -> tuple[np.ndarray, np.ndarray]:
    """Pose {W}->{C0} of each of F frames: SQPnP under K_c on the masked points. (F, 3) each."""
    F = len(points_2d)
    rvec, tvec = np.empty((F, 3)), np.empty((F, 3))
    for b in range(F):
        m = mask[b]
        if m.sum() < 4:
            raise InputError(f"frame {b}: {int(m.sum())} inference points, the C0 pose needs >= 4")
        rvec[b], tvec[b] = solve_pnp_start(points_2d[b][m], points_3d[b][m], K_c)
    return rvec, tvec


def point_features(points_2d, points_3d, K_c, rvec, tvec) -> np.ndarray:
    """(F, N, 5) raw [dx, dy, X, Y, 1/Z] (px, px, mm, mm, 1/mm) in {C0}; unmasked values are arbitrary."""
    Xc = np.einsum("fij,fnj->fni", rvec_to_matrix(rvec), points_3d) + tvec[:, None, :]
    inv_z = 1.0 / Xc[..., 2]
    fx, fy, cx, cy = k_params(K_c)
    dx = fx * Xc[..., 0] * inv_z + cx - points_2d[..., 0]
    dy = fy * Xc[..., 1] * inv_z + cy - points_2d[..., 1]
    return np.stack([dx, dy, Xc[..., 0], Xc[..., 1], inv_z], axis=-1)


def grid_features(points_2d, points_3d, mask, K_c, image_size, spec: FeatureSpec, *, poses=None) -> np.ndarray:
    """The flattened, scaled grid feature of F frames: (F, spec.size) float64.

    points_2d (F, N, 2) px; points_3d (F, N, 3) mm in {W}; mask (F, N) bool, the inference
    points; K_c (3, 3) the prior; image_size (width, height) px. ``poses`` (rvec, tvec) of
    {W}->{C0} may be passed when already known (else solved here with SQPnP).
    """
    points_2d = np.asarray(points_2d, dtype=np.float64)
    points_3d = np.asarray(points_3d, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    F, N = mask.shape
    rvec, tvec = poses if poses is not None else poses_c0(points_2d, points_3d, mask, K_c)
    safe_2d = np.where(mask[..., None], points_2d, 0.0)
    safe_3d = np.where(mask[..., None], points_3d, 0.0)
    feats = point_features(safe_2d, safe_3d, K_c, rvec, tvec)
    keep = [CHANNELS.index(c) for c in spec.channels]
    feats = feats[..., keep] * np.array([spec.scale[c] for c in spec.channels])
    n_cells = spec.grid.n_cells
    cells = spec.grid.cell_index(safe_2d, image_size) + n_cells * np.arange(F)[:, None]
    cells, feats = cells[mask], feats[mask]
    counts = np.bincount(cells, minlength=F * n_cells).astype(np.float64)
    sums = np.stack([np.bincount(cells, weights=feats[:, c], minlength=F * n_cells) for c in range(len(keep))], -1)
    means = sums / np.maximum(counts, 1.0)[:, None]
    return means.reshape(F, n_cells * len(keep))
