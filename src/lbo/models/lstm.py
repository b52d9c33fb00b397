"""The paper's LSTM observer (section III-B-2): stacked LSTM layers, then two dense layers."""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import torch
from torch import nn

from lbo.core.checks import integer
from lbo.core.errors import LboError
from lbo.models.cnn import POOL, xavier_init

#: PyTorch stacks the four gate matrices as (input, forget, cell, output).
_N_GATES = 4
_FORGET = 1


def _init_lstm(lstm: nn.LSTM) -> None:
    """Xavier-uniform per gate matrix, zero biases except a forget-gate bias of 1.

    Each gate is its own linear map, so each (hidden, in) block gets Xavier bounds of its own
    rather than those of the stacked (4 * hidden, in) matrix. The forget-gate bias of 1 makes
    the cell keep its state at the start of training, so gradients reach the early steps of
    long windows (Jozefowicz et al., 2015).
    """
    hidden = lstm.hidden_size
    for name, p in lstm.named_parameters():
        if name.startswith("weight"):
            for gate in p.data.split(hidden, dim=0):
                nn.init.xavier_uniform_(gate)
        else:
            nn.init.zeros_(p)
            if name.startswith("bias_ih"):
                nn.init.ones_(p.data[_FORGET * hidden:(_FORGET + 1) * hidden])


class WindowLSTM(nn.Module):
    """LSTM observer: a window of measurements and inputs -> the state at its last step.

    One single-layer ``nn.LSTM`` per entry of ``hidden_sizes`` (the paper: 8, 16, 32, 32 units),
    then a sigmoid dense layer and a linear output layer on the last time step's output.

    Parameters
    ----------
    window : N, the number of time steps per window. The LSTM runs on any length; the value is
        checked (>= 4, as for the CNN) so that both observers take the same arguments.
    hidden_sizes : units of each stacked LSTM layer.
    dense_units : width of the hidden dense layer.
    in_features : channels per time step.
    """

    def __init__(self, window: int, *, hidden_sizes: Sequence[int] = (8, 16, 32, 32),
                 dense_units: int = 64, in_features: int = 5) -> None:
        super().__init__()
        self.window = integer(window, "window", POOL)
        if isinstance(hidden_sizes, (str, bytes)) or not isinstance(hidden_sizes, Sequence) \
                or len(hidden_sizes) == 0:
            raise LboError(f"hidden_sizes: expected a non-empty list of integers >= 1, "
                           f"got {hidden_sizes!r}")
        sizes = [integer(h, "hidden_sizes", 1) for h in hidden_sizes]
        dense_units = integer(dense_units, "dense_units", 1)
        self.in_features = integer(in_features, "in_features", 1)
        self.hidden_sizes = tuple(sizes)
        self.lstms = nn.ModuleList(
            nn.LSTM(n_in, n_out, batch_first=True)
            for n_in, n_out in zip([self.in_features, *sizes[:-1]], sizes)
        )
        # Linear output: the targets are normalised regression values of either sign, which a
        # sigmoid output (range (0, 1)) cannot represent.
        self.head = nn.Sequential(
            nn.Linear(sizes[-1], dense_units),
            nn.Sigmoid(),
            nn.Linear(dense_units, 3),
        )
        xavier_init(self.head)
        for lstm in self.lstms:
            _init_lstm(cast(nn.LSTM, lstm))  # the LSTMs made just above

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N, in_features) float32 windows -> (B, 3) state estimates."""
        h = x
        for lstm in self.lstms:
            h, _ = lstm(h)
        return self.head(h[:, -1])
