"""The settings of `dimenet train` and `dimenet reproduce`, without torch.

The command line reads its defaults from these dataclasses (training/commands.py), so
`dimenet train --help` imports no torch and states no default of its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Optional

from dimenet.runtime.cli.arguments import finite_float_in, integer_in
from dimenet.runtime.errors import InputError
from dimenet.runtime.rectify.encoders.grid import VARIANTS
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.spec import head_problem

# The flags are range-checked by their argparse types, so a bad value is refused before torch is imported;
# a fleet manifest's values go through the same types (training/fleet.py).
MAX_EPOCHS = 100_000  # the paper's models train 600; 2**40 would run for ever
MAX_FOCAL_WEIGHT = 1000.0  # 1e300 overflows the loss (NaN poses)
MAX_TRAIN_FRAMES = 1_000_000
FEATURE_VARIANTS = tuple(VARIANTS)  # paper Table 3
epochs = integer_in(1, MAX_EPOCHS)
focal_weight = finite_float_in(0.0, MAX_FOCAL_WEIGHT)
train_frames = integer_in(2, MAX_TRAIN_FRAMES)
k_c_error = finite_float_in(0.0, 1.0)
plane_share = finite_float_in(0.0, 1.0)
# The epochs of each training of a --quick run (train, fleet train, reproduce): a smoke run that checks a command
# end to end, as the README's and the help's examples are checked (tests/readme_examples.py).
QUICK_EPOCHS = 1
QUICK_CAMERAS = 2  # and the cameras of each of reproduce's held-out families


@dataclass(frozen=True)
class TrainConfig:
    # What the network reads (grid, variant, data_step, moments; rectify.features); its depth_mm is the data's: the
    # trainer sets it for a generic model and clears it for a device model.
    features: FeatureSpec = field(default_factory=FeatureSpec)
    head: str = "mlp"  # "gated_step": Delta K = MLP + a learned gate times the data step (training.model)
    epochs: int = 600
    batch_size: int = 32
    lr: float = 2e-3
    weight_decay: float = 1e-2  # AdamW's own default: keeps the long schedule from overfitting the rig
    hidden: tuple = (256, 128)
    seed: int = 0
    val_fraction: float = 0.15  # of train, held back when the dataset has no val split
    min_points: int = 64
    max_eta: float = 0.8
    max_noise_px: float = 3.0  # per-frame extra 2D noise drawn from U(0, max), px
    resynthesis: float = 0.75  # share of train frames re-imaged under another frame's principal point
    cluster_share: float = 0.25  # share of frames whose inference points shrink to hand-labelled-like clusters
    cluster_points: tuple = (40, 100)  # how many points those clusters keep, drawn uniformly
    max_label_noise_px: float = 6.0  # per-frame label noise on the clustered points drawn from U(0, max), px
    plane_share: float = 0.0  # share of frames whose inference points shrink to one plane's (units.augment)
    # Epochs without val improvement before stopping; None (default): the whole cosine schedule
    # runs (stopping at 150 cost one seed 5 points of ipad rho) and the best val epoch is kept.
    patience: Optional[int] = None
    full_share: float = 0.4  # share of frames keeping all their inference points and every cell
    focal_weight: float = 0.03  # weight of the focal term: squared error (px^2) of (fx, fy) against K*
    train_frames: Optional[int] = None  # keep only the first N train frames of each dataset, in file order
    # Share of the cameras that, each epoch, train under a factory-like K_c (trainer.factory_k_c) instead of their
    # calibrated one, so the network learns to correct the K_c users have (ARKit's, Camera2's); 0: the paper's.
    k_c_error: float = 0.0
    # Learning rate when starting from a model's weights (--init): a tenth of lr keeps what the
    # init knows (at lr, 30 galaxy-s8 frames took the default's natural rho 76 -> 66 %; METHOD.md).
    fine_tune_lr: float = 2e-4

    def __post_init__(self) -> None:
        problem = head_problem(self.head, self.features.data_step, "--data-step (data_step in a fleet manifest)")
        if problem:
            raise InputError(problem)

    def to_dict(self) -> dict:
        """The settings as JSON values (checkpoints, provenance, fleet records): the features as a spec's."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        return {**d, "features": self.features.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """``to_dict``'s settings again (JSON's lists back to tuples)."""
        tuples = {f.name for f in fields(cls) if isinstance(f.default, tuple)}
        settings = {k: tuple(v) if k in tuples else v for k, v in d.items()}
        return cls(**{**settings, "features": FeatureSpec.from_dict(d["features"])})


@dataclass(frozen=True)
class ReproduceConfig:
    out_dir: Path
    epochs: int = 600
    ablation_epochs: int = 150
    seed: int = 0
    held_out_cameras: Optional[int] = None  # cameras of each held-out family (None: all; --quick: QUICK_CAMERAS)
