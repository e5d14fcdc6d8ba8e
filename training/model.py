"""The DIME-Net MLP (paper Sec. IV-B): flattened grid feature -> Delta K = (dfx, dfy, dcx, dcy) px.

Three fully connected layers without biases and GELU activations (GELU(0) = 0), so a zero
feature gives exactly Delta K = 0, i.e. K = K_c "due to lack of information" (paper), in
torch and in the exported ONNX graph alike.
"""

from __future__ import annotations

import torch
from torch import nn

# The network works in units of OUTPUT_SCALE_PX pixels, keeping weights of order 1.
OUTPUT_SCALE_PX = 10.0


class DimeNet(nn.Module):
    def __init__(self, in_features: int, hidden: tuple = (256, 128)) -> None:
        super().__init__()
        h1, h2 = hidden
        self.hidden = (h1, h2)
        self.fc1 = nn.Linear(in_features, h1, bias=False)
        self.fc2 = nn.Linear(h1, h2, bias=False)
        self.fc3 = nn.Linear(h2, 4, bias=False)
        self.act = nn.GELU()

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features (B, 5*u*v) float32 -> delta_k (B, 4) px: (dfx, dfy, dcx, dcy)."""
        return self.fc3(self.act(self.fc2(self.act(self.fc1(features))))) * OUTPUT_SCALE_PX
