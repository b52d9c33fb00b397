"""The paper's CNN observer (section III-B-1): separate measurement and input branches, merged."""

from __future__ import annotations

import torch
from torch import nn

from lbo.core.checks import integer
from lbo.core.errors import LboError

#: Channels 0..2 of a window are the measurements [x_m, y_m, psi_m]; the rest are inputs.
N_MEAS = 3
#: The paper's kernels: 5x1 along time, 4x1 pooling along time, 1x3 across features.
TIME_KERNEL = 5
POOL = 4
FEATURE_KERNEL = 3


#: Activations: the paper's sigmoid, or the same curve shifted to (-0.5, 0.5).
ACTIVATIONS = ("sigmoid", "centred_sigmoid")


class CentredSigmoid(nn.Module):
    """sigmoid(x) - 0.5: the paper's activation with zero-mean outputs.

    The layers and sizes stay the paper's, and the shift is absorbed by the next layer's bias
    (max pooling commutes with it); only at the zero-padded borders of a convolution does the
    padding now stand for the sigmoid's midpoint instead of 0. What changes is the
    conditioning: a sigmoid layer feeds the dense layer 20 N inputs near 0.5, so the gradients
    of all its weights share one sign, Adam moves each by about lr per step, and the
    pre-activation moves by about lr * 10 N; at N >= 60 and the lr tuned at N=20 that
    saturates the dense layer within a few steps and the CNN outputs the mean.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x) - 0.5


def make_activation(name: str) -> nn.Module:
    """An activation of :data:`ACTIVATIONS` by name."""
    if name not in ACTIVATIONS:
        raise LboError(f"model.activation: expected one of {', '.join(ACTIVATIONS)}, "
                       f"got {name!r}")
    return nn.Sigmoid() if name == "sigmoid" else CentredSigmoid()


def xavier_init(module: nn.Module) -> None:
    """Xavier-uniform weights and zero biases for every conv and dense layer (paper III-B)."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


class _Branch(nn.Module):
    """One branch: a (time x feature) map with one channel -> flat feature vector.

    Shapes: (B, N, F) -> (B, feature_channels * (N // 4) * F).
    """

    def __init__(self, conv_channels: int, feature_channels: int, act: str) -> None:
        super().__init__()
        # Padding keeps the time length through the 5x1 convolutions and the feature count
        # through the 1x3 ones, so the 2-feature input branch works like the 3-feature one.
        self.layers = nn.Sequential(
            nn.Conv2d(1, conv_channels, (TIME_KERNEL, 1), padding=(TIME_KERNEL // 2, 0)),
            make_activation(act),
            nn.Conv2d(conv_channels, conv_channels, (TIME_KERNEL, 1),
                      padding=(TIME_KERNEL // 2, 0)),
            make_activation(act),
            nn.MaxPool2d((POOL, 1)),
            nn.Conv2d(conv_channels, feature_channels, (1, FEATURE_KERNEL),
                      padding=(0, FEATURE_KERNEL // 2)),
            make_activation(act),
            nn.Conv2d(feature_channels, feature_channels, (1, FEATURE_KERNEL),
                      padding=(0, FEATURE_KERNEL // 2)),
            make_activation(act),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.flatten(self.layers(x.unsqueeze(1)), 1)


class WindowCNN(nn.Module):
    """CNN observer: a window of measurements and inputs -> the state at its last step.

    Measurements (channels 0..2) and inputs (channels 3..) each pass through their own branch
    of two 5x1 convolutions along time, a 4x1 max pooling along time and two 1x3 convolutions
    across features, all with sigmoid activations. The flattened branches are concatenated and
    go through a sigmoid dense layer and a linear output layer.

    Parameters
    ----------
    window : N, the number of time steps per window; >= 4 so that pooling leaves N // 4 >= 1.
    conv_channels : channels of the two 5x1 (time) convolutions.
    feature_channels : channels of the two 1x3 (feature) convolutions.
    dense_units : width of the hidden dense layer.
    in_features : channels per time step; 3 measurements plus ``in_features - 3`` inputs.
    activation : ``"sigmoid"`` (the paper's) or ``"centred_sigmoid"`` (sigmoid - 0.5, the same
        function class, trains at every N with one learning rate; see :class:`CentredSigmoid`).
        The default stays ``"sigmoid"`` so that checkpoints saved without the key keep their
        meaning; ``conf/model/cnn.yaml`` picks the centred one.
    """

    def __init__(self, window: int, *, conv_channels: int = 16, feature_channels: int = 16,
                 dense_units: int = 64, in_features: int = 5,
                 activation: str = "sigmoid") -> None:
        super().__init__()
        self.window = integer(window, "window", POOL)
        conv_channels = integer(conv_channels, "conv_channels", 1)
        feature_channels = integer(feature_channels, "feature_channels", 1)
        dense_units = integer(dense_units, "dense_units", 1)
        self.in_features = integer(in_features, "in_features", N_MEAS + 1)
        self.n_meas = N_MEAS  # an attribute, because TorchScript cannot read module globals
        make_activation(activation)  # one line naming the field for an unknown name
        self.measurements = _Branch(conv_channels, feature_channels, activation)
        self.inputs = _Branch(conv_channels, feature_channels, activation)
        flat = feature_channels * (self.window // POOL) * self.in_features
        # The output layer is linear: the targets are normalised regression values of either
        # sign, which a sigmoid output (range (0, 1)) cannot represent.
        self.head = nn.Sequential(
            nn.Linear(flat, dense_units),
            make_activation(activation),
            nn.Linear(dense_units, 3),
        )
        xavier_init(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N, in_features) float32 windows -> (B, 3) state estimates."""
        meas = self.measurements(x[:, :, : self.n_meas])
        inputs = self.inputs(x[:, :, self.n_meas :])
        return self.head(torch.cat([meas, inputs], dim=1))
