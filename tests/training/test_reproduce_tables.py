"""`dimenet reproduce`'s baseline cases (training/reproduce/tables.py): the prior oracle goes beside the modes
where the frames carry what it needs, and a case whose label noise is unknown runs the other methods."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from helpers import DEVICE_MODEL

from dimenet.runtime.evaluation.conditions import add_noise
from dimenet.runtime.evaluation.prior_oracle import PRIOR_ORACLE
from dimenet.runtime.sim.simulator import simulate
from dimenet.training.reproduce import tables


def test_a_case_without_label_noise_runs_every_other_method_and_natural_frames_get_the_prior_oracle():
    ds = simulate("galaxy-s8", seed=2, natural_frames=6, platform_k=True)
    rig = ds.select((ds.scene == "rig") & (ds.split == "test"))
    noisy = add_noise(rig, 1.0, 0.2, np.random.default_rng(1))  # 3D noise: the label noise is unknown
    assert noisy.label_noise_px is None
    case = tables._baseline(noisy, str(DEVICE_MODEL))
    assert PRIOR_ORACLE not in case["methods"] and {"platform", "dimenet", "map", "oracle"} <= set(case["methods"])
    natural = tables._baseline(ds.select(ds.scene == "natural"), str(DEVICE_MODEL))
    assert natural["methods"][PRIOR_ORACLE]["avg_e"] > 0
