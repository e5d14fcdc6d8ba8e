"""Torch backend of dimenet.runtime.evaluation.predictor: a RUN_DIR as a Predictor (entry point `run_dir`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dimenet.runtime.evaluation.predictor import Predictor
from dimenet.runtime.rectify.spec import ModelSpec

from .model import DimeNet
from .run_dir import load_run


def torch_predictor(model: DimeNet, spec: ModelSpec, source: str) -> Predictor:
    """A Predictor running the torch model (in eval mode, no gradients)."""
    model.eval()

    def delta_k(features: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(np.ascontiguousarray(features, dtype=np.float32))).double().numpy()

    return Predictor(spec=spec, delta_k=delta_k, source=source)


def load_run_predictor(run_dir: str | Path) -> Predictor:
    model, spec = load_run(run_dir)
    return torch_predictor(model, spec, str(run_dir))
