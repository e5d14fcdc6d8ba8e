"""Torch backend of dimenet.runtime.predictor: a RUN_DIR as a Predictor (entry point `run_dir`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dimenet.runtime.predictor import Predictor

from .run_dir import load_run


def load_run_predictor(run_dir: str | Path) -> Predictor:
    model, spec = load_run(run_dir)

    def delta_k(features: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(np.ascontiguousarray(features, dtype=np.float32))).double().numpy()

    return Predictor(spec=spec, delta_k=delta_k, source=str(run_dir))
