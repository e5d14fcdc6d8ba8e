"""The DIME-Net MLP (paper Sec. IV-B): flattened grid feature -> Delta K = (dfx, dfy, dcx, dcy) px.

Three fully connected layers without biases and GELU activations (GELU(0) = 0), so a zero
feature gives exactly Delta K = 0, i.e. K = K_c "due to lack of information" (paper), in
torch and in the exported ONNX graph alike.

The gated step head (``ModelSpec.head == "gated_step"``, needs ``FeatureSpec.data_step``; not
the paper's): Delta K = MLP(feature) + sigmoid(gate(h)) * the feature's own data step, h the last
hidden layer, the gate one linear layer with a bias per parameter. The network starts from the
frame's own Gauss-Newton step and learns how far to trust it and what to add; a zero feature
still gives Delta K = 0 (its step is 0).
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from dimenet.runtime.rectify.encoders import spans

# The network works in units of OUTPUT_SCALE_PX pixels, keeping weights of order 1.
OUTPUT_SCALE_PX = 10.0
# The gate's starting bias: sigmoid(2) = 0.88 of the step at the first epoch.
GATE_START = 2.0


class DimeNet(nn.Module):
    def __init__(self, in_features: int, hidden: tuple = (256, 128), step: Optional[tuple] = None) -> None:
        """step: None (the paper's MLP) or the gated step head's (index of the step's first feature,
        the feature's scale in 1/px of Delta K)."""
        super().__init__()
        h1, h2 = hidden
        self.hidden = (h1, h2)
        self.fc1 = nn.Linear(in_features, h1, bias=False)
        self.fc2 = nn.Linear(h1, h2, bias=False)
        self.fc3 = nn.Linear(h2, 4, bias=False)
        self.act = nn.GELU()
        self.gate = None
        if step is not None:
            first, scale_per_px = step
            self.gate = nn.Linear(h2, 4)
            nn.init.constant_(self.gate.bias, GATE_START)
            pick = torch.zeros(in_features, 4)
            pick[first + torch.arange(4), torch.arange(4)] = 1.0 / (scale_per_px * OUTPUT_SCALE_PX)
            self.register_buffer("step_pick", pick)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features (B, D) float32 -> delta_k (B, 4) px: (dfx, dfy, dcx, dcy)."""
        h = self.act(self.fc2(self.act(self.fc1(features))))
        out = self.fc3(h)
        if self.gate is not None:
            out = out + torch.sigmoid(self.gate(h)) * (features @ self.step_pick)
        return out * OUTPUT_SCALE_PX


def dime_net(features, hidden: tuple, head: str) -> DimeNet:
    """The DimeNet of a feature (``rectify.features.FeatureSpec``), hidden widths and head (a
    ModelSpec's ``features``, ``hidden``, ``head``)."""
    step = (spans(features)["data_step"].start, features.scale["dx"]) if head == "gated_step" else None
    return DimeNet(features.size, hidden, step)
