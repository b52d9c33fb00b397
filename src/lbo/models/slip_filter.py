"""A learned side-slip filter: the linear single-track Kalman filter whose tyres and noise small
networks learn (the robust observer's idea, a filter that learns what its model misses, on the
lateral body).

The state is ``x = [beta, r]`` (rad, rad/s), the inputs the speed vx and the road wheels'
steering delta, the measurements ``y = [ay, r]`` (m/s^2, rad/s), as in
:func:`lbo.filters.lateral.linear_single_track`. The prediction to row k takes one Euler step
of dt on row k-1's speed and steering:

    a_f = delta - beta - l_f r / vx,          a_r = -beta + l_r r / vx        (slip angles)
    f_f = C_f a_f / m + g_f,                  f_r = C_r a_r / m + g_r         (per unit mass)
    beta' = (f_f + f_r) / vx - r,             r' = m (l_f f_f - l_r f_r) / I_z,
    a_y = f_f + f_r,

the car's published parameters (the :class:`~lbo.models.slip.Prior`'s) and linear tyres,
corrected by the tyre network ``g = (g_f, g_r)`` (m/s^2) of the slip angles and the speed: what
the linear tyres miss where they saturate. The noise network scales the prior's noise per row
from what the car measures there (vx, delta, ay_m, r_m): the process noise, the steering's
noise through the model (``Q = exp(2 s_q) q^2 b b^T``, b the step's derivative in delta), and
each measurement's variance (``exp(2 s_ay)``, ``exp(2 s_r)``). Both networks' last layers start
at zero, so that an untrained filter is the linear Kalman filter it corrects (tested to 1e-9).
It is never told the tyres' limit, and the side slip's reference is its loss's target only.

The Jacobians are central differences (float64); the update is the masked Joseph update every
torch filter of lbo uses (:func:`lbo.models.update.masked_update`). Unlike the side-slip
network (:mod:`lbo.models.slip`) it gives its estimate's covariance. :class:`FilterObserver` runs
a whole log (:meth:`~FilterObserver.run`) or row by row (:meth:`~FilterObserver.stream`), the
same step either way.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch
from torch import nn

from lbo.filters.lateral import LateralEstimate
from lbo.models import slip
from lbo.models.slip import Prior, read_checkpoint
from lbo.models.update import masked_update

NAME = "slip_filter"
"""``model.name`` of the learned side-slip filter."""
PARAMETERS = ("hidden", "prior_gain", "sequence", "warmup")
"""Its ``model`` settings: the networks' width, the prior's noise gain, and the training
sequences' rows and the rows at each one's start that the loss leaves out."""
SIDE_SLIP = {slip.NAME: slip.PARAMETERS, NAME: PARAMETERS}
"""The side-slip observers' ``model.name`` and their ``model`` settings: the network of
:mod:`lbo.models.slip` and this filter. They learn on the side-slip run and its kind alone."""
FD_STEP = 1e-6
"""Central-difference step in beta (rad), r (rad/s) and delta (rad)."""
P0 = 1e4
"""The first row's variance of each state, as the linear filter's (the state starts at 0)."""
_SCALES = (30.0, 0.1, 10.0, 0.5)
"""What the noise network divides vx (m/s), delta (rad), ay_m (m/s^2) and r_m (rad/s) by: each
of order one on a car near its limit."""
_PREDICTED = ((0.0, 0.0), (FD_STEP, 0.0), (-FD_STEP, 0.0), (0.0, FD_STEP), (0.0, -FD_STEP),
              (0.0, 0.0), (0.0, 0.0))
_PREDICTED_DELTA = (0.0, 0.0, 0.0, 0.0, 0.0, FD_STEP, -FD_STEP)
"""The states' and the steering's offsets at which a step's Jacobians are differenced."""
_SLIP_SCALE = 0.1
"""What the tyre network divides the slip angles (rad) by; it divides vx by 30 m/s."""


def _mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    first, middle, last = (nn.Linear(inputs, hidden), nn.Linear(hidden, hidden),
                           nn.Linear(hidden, outputs))  # drawn in this order, as seeded
    nn.init.zeros_(last.weight)  # the linear filter at the start: no correction, the
    nn.init.zeros_(last.bias)    # prior's noise
    return nn.Sequential(first, nn.Tanh(), middle, nn.Tanh(), last)


@dataclass
class FilterState:
    """A filter carried between rows: x (B, 2), P (B, 2, 2), the previous row's vx, delta
    (B,) and its process-noise scale (B,); ``last`` None before the first row."""

    x: torch.Tensor
    P: torch.Tensor
    last: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None


class LateralFilter(nn.Module):
    """The filter, float64: :meth:`forward` over (B, T) logs, :meth:`step` one row.

    Parameters
    ----------
    prior : the car's published parameters, the prior's noise and dt.
    hidden : units of each network's two hidden layers.
    """

    if TYPE_CHECKING:  # buffers registered by name, for the type checker
        offsets: torch.Tensor
        delta_offsets: torch.Tensor
        row_scales: torch.Tensor

    def __init__(self, prior: Prior, hidden: int = 16) -> None:
        super().__init__()
        self.prior, self.hidden = prior, int(hidden)
        c = prior.car  # plain floats: a checkpoint holds them in its prior
        self.car = (c.mass, c.yaw_inertia, c.l_f, c.l_r, c.c_f, c.c_r)
        self.tyres = _mlp(3, self.hidden, 2)
        self.noise = _mlp(4, self.hidden, 3)
        # constants of every step, made once and moved with the module (not in its state)
        self.register_buffer("offsets", torch.tensor(_PREDICTED), persistent=False)
        self.register_buffer("delta_offsets", torch.tensor(_PREDICTED_DELTA), persistent=False)
        self.register_buffer("row_scales", torch.tensor(_SCALES), persistent=False)
        self.double()

    def _rates(self, x: torch.Tensor, vx: torch.Tensor, delta: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """(beta', r') (..., 2) and a_y (...,) at states x (..., 2), inputs (...,)."""
        m, iz, lf, lr, cf, cr = self.car
        beta, r = x[..., 0], x[..., 1]
        a_f = delta - beta - lf * r / vx
        a_r = -beta + lr * r / vx
        g = self.tyres(torch.stack([a_f / _SLIP_SCALE, a_r / _SLIP_SCALE,
                                    (vx / 30.0).expand_as(a_f)], -1))
        f_f, f_r = cf * a_f / m + g[..., 0], cr * a_r / m + g[..., 1]
        return torch.stack([(f_f + f_r) / vx - r, m * (lf * f_f - lr * f_r) / iz], -1), f_f + f_r

    def noise_scales(self, vx: torch.Tensor, delta: torch.Tensor, y: torch.Tensor
                     ) -> torch.Tensor:
        """(..., 3) log-scales ``[s_q, s_ay, s_r]`` of each row's noise, from its vx, delta
        (...,) and measurements y (..., 2); a channel not held (NaN) reads as 0."""
        rows = torch.stack([vx, delta, torch.nan_to_num(y[..., 0]),
                            torch.nan_to_num(y[..., 1])], -1)
        return self.noise(rows / self.row_scales)

    def _predict(self, s: FilterState, vx: torch.Tensor, delta: torch.Tensor, s_q: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """One Euler step from the state s on inputs (B,) with process scale s_q (B,)."""
        dt, h = self.prior.dt, FD_STEP
        # x, x +- h e_i, and x at delta +- h: one call of the tyre network for all seven
        xs = s.x[:, None] + self.offsets
        ds = delta[:, None] + self.delta_offsets
        nxt = xs + dt * self._rates(xs, vx[:, None], ds)[0]
        F = torch.stack([nxt[:, 1] - nxt[:, 2], nxt[:, 3] - nxt[:, 4]], -1) / (2 * h)
        b = (nxt[:, 5] - nxt[:, 6]) / (2 * h)
        q2 = (self.prior.noise.delta * torch.exp(s_q)) ** 2
        P = F @ s.P @ F.transpose(1, 2) + q2[:, None, None] * b[:, :, None] * b[:, None, :]
        return nxt[:, 0], P

    def _measure(self, x: torch.Tensor, vx: torch.Tensor, delta: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """The measurements [ay, r] (B, 2) at states x (B, 2) and their Jacobian (B, 2, 2)."""
        xs = x[:, None] + self.offsets[:5]
        ay = self._rates(xs, vx[:, None], delta[:, None])[1]
        h = torch.stack([ay, xs[..., 1]], -1)
        H = torch.stack([h[:, 1] - h[:, 2], h[:, 3] - h[:, 4]], -1) / (2 * FD_STEP)
        return h[:, 0], H

    def start(self, batch: int, device: torch.device | None = None) -> FilterState:
        """The state before the first row: zero, variance :data:`P0` (the linear filter's)."""
        eye = torch.eye(2, dtype=torch.float64, device=device)
        return FilterState(torch.zeros(batch, 2, dtype=torch.float64, device=device),
                           (eye * P0).expand(batch, 2, 2).clone())

    def step(self, s: FilterState, vx: torch.Tensor, delta: torch.Tensor, y: torch.Tensor,
             scales: torch.Tensor | None = None) -> FilterState:
        """The filter at this row, from s at the row before: inputs (B,), measurements
        y (B, 2) [ay, r] (a NaN channel is not held); ``scales`` (B, 3) the row's
        :meth:`noise_scales`, if made already. The first row is the start itself, as in the
        linear filter; each later row predicts on the row before's inputs and updates with its
        own measurements."""
        if scales is None:
            scales = self.noise_scales(vx, delta, y)
        if s.last is None:
            return FilterState(s.x, s.P, (vx, delta, scales[:, 0]))
        x, P = self._advance(s, vx, delta, y, scales)
        return FilterState(x, P, (vx, delta, scales[:, 0]))

    def _advance(self, s: FilterState, vx: torch.Tensor, delta: torch.Tensor, y: torch.Tensor,
                 scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x (B, 2), P (B, 2, 2) at this row from s (which holds the row before's inputs):
        predict, then update with the measurements held, R from the row's noise scales
        (B, 3). Written as ONNX exports it (:class:`StepGraph`): R without diag_embed."""
        x, P = self._predict(s, *cast(tuple, s.last))
        h, H = self._measure(x, vx, delta)
        held = torch.isfinite(y)
        noise = self.prior.noise
        var_ay = (noise.ay * torch.exp(scales[:, 1])) ** 2
        var_r = (noise.r * torch.exp(scales[:, 2])) ** 2
        zero = torch.zeros_like(var_ay)
        R = torch.stack([torch.stack([var_ay, zero], -1), torch.stack([zero, var_r], -1)], -2)
        return masked_update(x, P, torch.where(held, y - h, torch.zeros_like(h)), R, H,
                             held.to(x.dtype))

    def forward(self, vx: torch.Tensor, delta: torch.Tensor, y: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Estimates of B logs: vx, delta (B, T), y (B, T, 2) float64 -> x (B, T, 2) and
        P (B, T, 2, 2)."""
        s = self.start(vx.shape[0], vx.device)
        scales = self.noise_scales(vx, delta, y)  # every row's at once
        xs, Ps = [], []
        for k in range(vx.shape[1]):  # a recursive filter: one step per row, every log at once
            s = self.step(s, vx[:, k], delta[:, k], y[:, k], scales[:, k])
            xs.append(s.x)
            Ps.append(s.P)
        return torch.stack(xs, 1), torch.stack(Ps, 1)


class StepGraph(nn.Module):
    """One row of the filter as a pure function of tensors, as ONNX exports it (float64, B
    filters): ``(x (B, 2), P (B, 2, 2), vx_prev, delta_prev, sq_prev (B,), started (B,),
    vx, delta (B,), y (B, 2)) -> (x, P, sq)``, the state after this row and this row's
    process-noise scale (the next row's ``sq_prev``). ``started`` 0 is the first row (the
    state holds, as :meth:`LateralFilter.step` starts); there pass this row's inputs as the
    previous ones, whose prediction is then computed and left out."""

    def __init__(self, net: LateralFilter) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor, P: torch.Tensor, vx_prev: torch.Tensor,
                delta_prev: torch.Tensor, sq_prev: torch.Tensor, started: torch.Tensor,
                vx: torch.Tensor, delta: torch.Tensor, y: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        scales = self.net.noise_scales(vx, delta, y)
        x_new, P_new = self.net._advance(FilterState(x, P, (vx_prev, delta_prev, sq_prev)),
                                         vx, delta, y, scales)
        go = started > 0.5
        return (torch.where(go[:, None], x_new, x), torch.where(go[:, None, None], P_new, P),
                scales[:, 0])


class FilterObserver:
    """The learned side-slip filter as an observer: :meth:`run` a whole log, :meth:`stream`
    one row at a time. ``prior`` is the linear filter it starts from (scored beside it)."""

    def __init__(self, net: LateralFilter) -> None:
        self.net, self.prior = net.eval(), net.prior

    def run(self, vx: np.ndarray, delta: np.ndarray, y: np.ndarray,
            prior: LateralEstimate | None = None) -> LateralEstimate:
        """Estimate a whole log: vx, delta (T,), y (T, 2) [ay_m, r_m] -> x (T, 2) [beta, r]
        and P (T, 2, 2). ``prior``: the linear filter's estimate, which the side-slip network
        corrects (:meth:`lbo.models.slip.SlipObserver.run`, called alike); not read here: this
        filter holds its own model of the car."""
        with torch.no_grad():
            x, P = self.net(*(torch.from_numpy(np.array(a, float))[None]
                              for a in (vx, delta, y)))
        return LateralEstimate(x[0].numpy(), P[0].numpy())

    def stream(self) -> FilterStream:
        return FilterStream(self.net)


class FilterStream:
    """One row at a time, as a car runs: :meth:`step` carries the filter one row."""

    def __init__(self, net: LateralFilter) -> None:
        self.net, self.state = net, net.start(1)

    def step(self, vx: float, delta: float, ay: float, r: float) -> np.ndarray:
        """The estimate [beta rad, r rad/s] (2,) at this row (a NaN measurement is not
        held)."""
        with torch.no_grad():
            self.state = self.net.step(self.state, torch.tensor([float(vx)], dtype=torch.float64),
                                       torch.tensor([float(delta)], dtype=torch.float64),
                                       torch.tensor([[ay, r]], dtype=torch.float64))
        return self.state.x[0].numpy().copy()


def load(path: str | os.PathLike) -> FilterObserver:
    """The observer of an ``lbo.train model=slip_filter`` checkpoint (tensors and plain
    containers only: nothing a file names is run)."""
    return observer(*read_checkpoint(path, NAME))


def load_any(path: str | os.PathLike) -> slip.SlipObserver | FilterObserver:
    """The observer of a checkpoint of any side-slip observer (:data:`SIDE_SLIP`)."""
    hp, state = read_checkpoint(path, *SIDE_SLIP)
    return (slip.observer if hp["name"] == slip.NAME else observer)(hp, state)


def observer(hp: Mapping[str, Any], state: Mapping[str, torch.Tensor]) -> FilterObserver:
    """The observer a checkpoint's hyperparameters and weights describe."""
    net = LateralFilter(Prior.from_dict(hp["prior"]), int(hp["hidden"]))
    net.load_state_dict(state)
    return FilterObserver(net)
