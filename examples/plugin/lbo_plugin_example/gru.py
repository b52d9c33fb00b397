"""A GRU over the window: a learned observer kept to lbo's model contract (docs/plugins.md).

The contract, in short: the class takes the window length first and its hyperparameters as
keywords (``in_features`` among them, for windows with a ``fix`` channel), reads (B, N, C)
float32 windows of normalised features and returns (B, 3) float32 normalised targets. lbo
does the rest: features, normalisation, training, evaluation, streaming, export.
"""

from __future__ import annotations

import torch
from torch import nn


class WindowGRU(nn.Module):
    """GRU layers over the window's steps, then a linear read-out of the last step.

    window : N, steps per window (the GRU takes any N; kept for the contract).
    in_features : channels per step (5, or 6 with the ``fix`` channel).
    hidden : units per GRU layer; layers : GRU layers.
    """

    def __init__(self, window: int, in_features: int = 5, hidden: int = 32,
                 layers: int = 1) -> None:
        super().__init__()
        if not (isinstance(hidden, int) and hidden >= 1 and isinstance(layers, int)
                and layers >= 1):
            raise ValueError(f"hidden and layers must be integers >= 1, got {hidden}, {layers}")
        self.window = int(window)
        self.gru = nn.GRU(in_features, hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N, in_features) -> (B, 3)."""
        out, _ = self.gru(x)
        return self.head(out[:, -1])
