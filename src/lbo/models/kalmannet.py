"""KalmanNet (architecture 2) and Split-KalmanNet around the kinematic bicycle: learned peers
of the literature, each a filter whose Kalman gain a network gives.

Revach, Shlezinger, Ni, Lopez Escoriza, van Sloun and Eldar, "KalmanNet: Neural Network Aided
Kalman Filtering for Partially Known Dynamics", IEEE Transactions on Signal Processing 70
(2022), 1532-1547. The filter keeps the model's prediction and learns the Kalman gain: at each
step the kinematic bicycle predicts the pose, and three GRUs, tracking what stand for the
process noise Q, the prior covariance Sigma and the innovation covariance S, read four
differences and output the gain K (3 x 3) that weighs the innovation:

- F1, the observation difference ``y_t - y_{t-1}``;
- F2, the innovation ``y_t - h(x_{t|t-1})``;
- F3, the forward evolution difference ``x_{t-1|t-1} - x_{t-2|t-2}``;
- F4, the forward update difference ``x_{t-1|t-1} - x_{t-1|t-2}``;

each in measurement sigmas and normalised to unit length, as the authors normalise them.
Architecture 2's flow: F3 -> GRU_Q; GRU_Q's state with F4 -> GRU_Sigma; GRU_Sigma's state
with F1 and F2 -> GRU_S; GRU_Sigma's and GRU_S's states -> K; and back, GRU_S's state with K
updates GRU_Sigma's.

Where this one differs from the published filter:

- **Two forms.** By default it runs over lbo's window of N steps from a cold start at the
  window's first fix and returns the last step's estimate, trained by lbo's window trainer
  (the gradient flows back through the N steps of each window). With ``tbptt=L`` it is
  trained as the authors train it, carried through each window in chunks of L steps
  (truncated back-propagation through time, :mod:`lbo.learn.sequence`), and then runs
  carried for the whole drive (:mod:`lbo.models.carried`).
- The GRUs' states start from learned vectors, not from priors of Q, Sigma and S.
- The gain is learned in units of the measurement sigmas at alpha = 1, ``K = D K~ D^-1`` with
  ``D = diag(sigma)``: the pose mixes metres and radians, and in sigma units the gain's
  entries, the cross terms included, are of one scale.
- The features are scaled to unit length smoothly near 0 (:func:`_unit`), where a plain
  normalisation's gradient is 1 / eps.
- A step without a fix (the ``fix`` channel) is a prediction: no gain, the GRUs hold.
- The GRU cells are written out (the same gates as ``torch.nn.GRUCell``), so that ONNX
  exports them.

Split-KalmanNet (Choi, Park, Kim, Kim and Kim, "Split-KalmanNet: A Robust Model-Based Deep
Learning Approach for State Estimation", IEEE Transactions on Vehicular Technology 72 (2023),
12326-12331) splits the gain in two, as a Kalman filter's is made: one GRU, reading the
state's differences (F3, F4), gives the prior covariance P; another, reading the
measurement's (F1, F2), gives the inverse innovation covariance S^-1; the gain is
``K = P H^T S^-1`` (H = I: the pose is measured). The split lets each network follow its own
noise: a change of the measurement noise moves S alone. It differs from the published one as
KalmanNet does above, and: one GRU layer each (the authors stack two), and P and S^-1 are
full 3 x 3 outputs in sigma units started at ``sqrt(gain) I`` each.

Both read ``"frame"`` features in metres and radians (the window in the frame of its latest
fix), as :class:`lbo.models.filternet.WindowFilter` does, and are never told alpha.

**Around the single-track body** (``body="single_track"``, for a car that slips): the state
is ``[x, y, psi, v_y, r]`` and the prediction is the learned single-track body of
:class:`lbo.models.motion.ProcessModel` (the robust observer's on ``experiment=dynamic``,
its constants learned beside the gain); the gain is 5 x 3 (the pose is measured, H = [I 0]),
F3 and F4 are over the five states, and the lateral speed and yaw rate start at the
kinematic bicycle's at the first fix.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, cast

import torch
from torch import nn
from torch.nn import functional as F

from lbo.core.checks import integer, number
from lbo.models.channels import window_channels
from lbo.models.frame import check_sigmas, frame_model
from lbo.models.motion import ProcessModel, bicycle_step
from lbo.models.poses import wrap_heading

N_MEASURED = 3
"""The measurement, and the kinematic body's state: the pose ``x, y, psi``."""
BODY_UNITS = (0.1, 0.02)
"""The units of the single-track body's lateral speed (m/s) and yaw rate (rad/s) in the gain
and the features: about the correction one fix makes to each at alpha = 1, so that the gain's
body rows are of the pose rows' scale."""


class _GRUCell(nn.Module):
    """``torch.nn.GRUCell``'s gates, written out (reset r, update z, candidate n)."""

    def __init__(self, inputs: int, hidden: int) -> None:
        super().__init__()
        self.x = nn.Linear(inputs, 3 * hidden)
        self.h = nn.Linear(hidden, 3 * hidden)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        xr, xz, xn = self.x(x).chunk(3, -1)
        hr, hz, hn = self.h(h).chunk(3, -1)
        r = torch.sigmoid(xr + hr)
        z = torch.sigmoid(xz + hz)
        n = torch.tanh(xn + r * hn)
        return (1 - z) * n + z * h


UNIT_FLOOR = 1e-3
"""The length (in measurement sigmas) below which a feature is not scaled up to unit length."""


def _unit(f: torch.Tensor, floor: float) -> torch.Tensor:
    """Each row scaled to unit length, as the authors normalise the features, but smoothly
    near 0 (``f / sqrt(|f|^2 + floor^2)``, floor :data:`UNIT_FLOOR`): the differences are
    exactly 0 at a window's first step and between fixes, where a plain normalisation's
    gradient is 1 / eps (1e12 with torch's; a first training with it, ``experiment=robust``,
    diverged in its first epoch)."""
    return f / torch.sqrt((f * f).sum(-1, keepdim=True) + floor * floor)


class _GainFilter(ProcessModel, nn.Module):
    """A filter over the window whose gain a network gives: the process model predicts,
    ``_gain`` reads the four differences (see the module) and its recurrent states, and
    returns the gain (B, n x 3) in units (the measurement sigmas, :data:`BODY_UNITS`) and the
    states it carries; a step without a fix predicts, and the states hold. The subclasses
    build the network."""

    if TYPE_CHECKING:  # buffers registered by name, for the type checker
        units: torch.Tensor
        state_units: torch.Tensor

    def _setup(self, window: int, dt: float, wheelbase: float,
               measurement_sigma: Sequence[float], in_features: int, body: str,
               body_lr: float, body_rear: float | None) -> None:
        frame_model(self, window, in_features, dt, wheelbase)
        self.build_process(0, body, body_lr, body_rear=body_rear)
        units = check_sigmas("measurement_sigma", measurement_sigma)
        self.register_buffer("units", torch.tensor(units))
        # not saved: derived, and checkpoints stored before it must still load
        self.register_buffer("state_units", torch.tensor(
            units + (BODY_UNITS if self.single_track else ())), persistent=False)
        # attributes: TorchScript reads no module-level number
        self.n_measured = N_MEASURED
        self.n_state = N_MEASURED + (2 if self.single_track else 0)
        self.unit_floor = UNIT_FLOOR

    def _start(self, b: int) -> list[torch.Tensor]:
        """The recurrent states (B, h) each, at a window's first step."""
        raise NotImplementedError

    def _gain(self, f1: torch.Tensor, f2: torch.Tensor, f3: torch.Tensor, f4: torch.Tensor,
              hidden: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The gain (B, 9) in sigma units, and the recurrent states after this step."""
        raise NotImplementedError

    def _predict(self, z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """One process-model step of (B, n) states with inputs u (B, 2) ``[V, delta]``."""
        if self.single_track:
            pose, _, _, body = self.predict_pose(z[:, :3], u[:, 0], u[:, 1], z[:, 3:])
            return torch.cat([pose, body], -1)
        return bicycle_step(z, u[:, 0], u[:, 1], self.dt, self.wheelbase)

    def _first(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The state (B, n) at a first fix y (B, 3) with inputs u (B, 2): the single-track
        body's lateral states the kinematic bicycle's."""
        if self.single_track:
            return torch.cat([y, self.body_start(u[:, 0], u[:, 1])], -1)
        return y

    def begin(self, y0: torch.Tensor, fix0: torch.Tensor, u0: torch.Tensor
              ) -> list[torch.Tensor]:
        """The filter's state at a sequence's first step: y0 (B, 3) its measured pose, fix0
        (B,) bool whether it holds one (the filter starts at the first fix), u0 (B, 2) its
        inputs ``[V, delta]``. The state is a list: the estimate (B, n), the two estimates
        before it, the last fix, whether it started, then the recurrent states;
        :meth:`advance` carries it."""
        z0 = self._first(y0, u0)
        return [z0, z0, z0, y0, fix0] + self._start(y0.shape[0])  # no unpacking: TorchScript

    def advance(self, state: list[torch.Tensor], u_prev: torch.Tensor, y: torch.Tensor,
                fix: torch.Tensor, u: torch.Tensor | None = None
                ) -> tuple[list[torch.Tensor], torch.Tensor]:
        """One step: the state of :meth:`begin` or of the step before, the inputs of the step
        before u_prev (B, 2) ``[V, delta]``, this step's measured pose y (B, 3) and fix (B,)
        bool (this step's inputs u are read at the next step, as u_prev). Returns the next
        state and the estimate (B, 3), heading wrapped."""
        # indexed, not unpacked: TorchScript cannot size a list's slice
        z, z_prev, z_prior_prev, y_last, started = state[0], state[1], state[2], state[3], state[4]
        hidden = state[5:]
        b = z.shape[0]
        prior = self._predict(z, u_prev)
        innovation = wrap_heading(y - prior[:, :3])
        # the four differences in units (metres and radians made comparable)
        f1 = _unit(wrap_heading(y - y_last) / self.units, self.unit_floor)
        f2 = _unit(innovation / self.units, self.unit_floor)
        f3 = _unit(wrap_heading(z - z_prev) / self.state_units, self.unit_floor)
        f4 = _unit(wrap_heading(z - z_prior_prev) / self.state_units, self.unit_floor)
        gain, after = self._gain(f1, f2, f3, f4, hidden)
        # K = D_n K~ D_m^-1: the innovation in sigmas, the correction back in metres, radians
        post = prior + self.state_units * (gain.view(b, self.n_state, self.n_measured)
                                           @ (innovation / self.units).unsqueeze(-1)).squeeze(-1)
        # a step with a fix updates (the first fix: the filter starts there); one without
        # predicts, and the recurrent states hold
        update = (fix & started)[:, None]
        first = (fix & ~started)[:, None]
        start = self._first(y, u_prev)  # the inputs of the step before: this step's are unread
        new = torch.where(first, start, torch.where(update, post, prior))
        hidden = [torch.where(update, h1, h0) for h1, h0 in zip(after, hidden)]
        y_last = torch.where(fix[:, None], y, y_last)
        state = [new, z, torch.where(first, start, prior), y_last, started | fix] + hidden
        return state, wrap_heading(new[:, :3])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N, 5|6) features -> (B, 3) pose in the frame of the window's latest fix."""
        w = window_channels(x)
        y, u = w.pose, w.inputs
        fix = w.fix > 0.5  # every row of a window without the fix channel
        state = self.begin(y[:, 0], fix[:, 0], u[:, 0])
        for k in range(1, x.shape[1]):
            state, _ = self.advance(state, u[:, k - 1], y[:, k], fix[:, k])
        return wrap_heading(state[0][:, :3])


class KalmanNet(_GainFilter):
    """KalmanNet (architecture 2) over a window, on the kinematic bicycle or the single-track
    body (see the module).

    Parameters
    ----------
    window : N, steps per window (>= 4).
    dt, wheelbase : the vehicle's sampling period (s) and wheelbase (m), for the prediction.
    measurement_sigma : (3,) the measurement sigmas at alpha = 1 (m, m, rad): the gain's
        units.
    in_features : channels per step: 5, or 6 with the ``fix`` channel (missing fixes).
    width : the GRUs' states hold ``width * n^2`` units (the authors' n^2, times this; n = 3,
        or 5 around the single-track body).
    hidden : width of the gain's hidden layer.
    gain : the gain's starting value, ``gain * [I 0]^T`` (a low-gain filter, not dead
        reckoning).
    body, body_lr : the process model, ``"kinematic"`` or ``"single_track"`` (see the module),
        and the single-track body's learning rate as a multiple of the optimiser's.
    body_rear : the single-track body's centre of gravity ahead of the rear axle (m), held
        where given; None learns it (:meth:`lbo.models.motion.ProcessModel.build_process`).
    """

    if TYPE_CHECKING:  # parameters registered by name, for the type checker
        h_q: torch.Tensor
        h_sigma: torch.Tensor
        h_s: torch.Tensor

    def __init__(self, window: int, *, dt: float = 0.02, wheelbase: float = 2.7,
                 measurement_sigma: Sequence[float] = (1.0, 1.0, 0.0174),
                 in_features: int = 5, width: int = 4, hidden: int = 64,
                 gain: float = 0.05, body: str = "kinematic", body_lr: float = 1.0,
                 body_rear: float | None = None) -> None:
        super().__init__()
        self._setup(window, dt, wheelbase, measurement_sigma, in_features, body, body_lr,
                    body_rear)
        width = integer(width, "model.width", 1)
        hidden = integer(hidden, "model.hidden", 1)
        gain = number(gain, "model.gain", low=0.0, high=1.0, form="a number in [0, 1]")
        n, m = self.n_state, self.n_measured
        h = width * n * n
        wide, wide_y = 5 * n, 5 * m  # the input layers' widths (the authors' in_mult = 5)
        self.fc_q = nn.Linear(n, wide)             # F3 -> GRU_Q
        self.fc_f4 = nn.Linear(n, wide)            # F4 -> GRU_Sigma
        self.fc_y = nn.Linear(2 * m, 2 * wide_y)   # F1, F2 -> GRU_S
        self.gru_q = _GRUCell(wide, h)
        self.gru_sigma = _GRUCell(h + wide, h)
        self.fc_sigma = nn.Linear(h, h)            # Sigma's state -> GRU_S
        self.gru_s = _GRUCell(h + 2 * wide_y, h)
        self.fc_gain = nn.Sequential(nn.Linear(2 * h, hidden), nn.ReLU(),
                                     nn.Linear(hidden, n * m))
        self.fc_back = nn.Linear(h + n * m, h)     # S's state and K -> back to Sigma's
        self.fc_sigma_back = nn.Linear(2 * h, h)
        for name in ("h_q", "h_sigma", "h_s"):
            self.register_parameter(name, nn.Parameter(torch.zeros(h)))
        head = cast(nn.Linear, self.fc_gain[-1])  # the Linear made just above
        nn.init.zeros_(head.weight)
        with torch.no_grad():
            head.bias.copy_(gain * torch.eye(n, m).flatten())

    def _start(self, b: int) -> list[torch.Tensor]:
        return [self.h_q.expand(b, -1), self.h_sigma.expand(b, -1), self.h_s.expand(b, -1)]

    def _gain(self, f1: torch.Tensor, f2: torch.Tensor, f3: torch.Tensor, f4: torch.Tensor,
              hidden: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        h_q, h_sigma, h_s = hidden
        q = self.gru_q(F.relu(self.fc_q(f3)), h_q)
        sigma = self.gru_sigma(torch.cat([q, F.relu(self.fc_f4(f4))], -1), h_sigma)
        s_in = torch.cat([F.relu(self.fc_sigma(sigma)), F.relu(self.fc_y(
            torch.cat([f1, f2], -1)))], -1)
        s = self.gru_s(s_in, h_s)
        gain = self.fc_gain(torch.cat([sigma, s], -1))
        back = F.relu(self.fc_back(torch.cat([s, gain], -1)))
        sigma = F.relu(self.fc_sigma_back(torch.cat([sigma, back], -1)))
        return gain, [q, sigma, s]


class SplitKalmanNet(_GainFilter):
    """Split-KalmanNet over a window, on the kinematic bicycle (see the module): the gain
    ``K = P S^-1`` of a prior covariance P that one GRU gives from the state's differences and
    an inverse innovation covariance S^-1 that another gives from the measurement's.

    Parameters
    ----------
    window, dt, wheelbase, measurement_sigma, in_features, body, body_lr, body_rear : as
        :class:`KalmanNet`'s.
    width : P's GRU holds ``width * n^2`` units, S's ``width * 9``.
    gain : the gain's starting value, ``gain * [I 0]^T`` (P and S^-1 each ``sqrt(gain) I``).
    """

    if TYPE_CHECKING:  # parameters registered by name, for the type checker
        h_p: torch.Tensor
        h_s: torch.Tensor

    def __init__(self, window: int, *, dt: float = 0.02, wheelbase: float = 2.7,
                 measurement_sigma: Sequence[float] = (1.0, 1.0, 0.0174),
                 in_features: int = 5, width: int = 4, gain: float = 0.05,
                 body: str = "kinematic", body_lr: float = 1.0,
                 body_rear: float | None = None) -> None:
        super().__init__()
        self._setup(window, dt, wheelbase, measurement_sigma, in_features, body, body_lr,
                    body_rear)
        width = integer(width, "model.width", 1)
        gain = number(gain, "model.gain", low=0.0, high=1.0, form="a number in [0, 1]")
        n, m = self.n_state, self.n_measured
        self.fc_state = nn.Linear(2 * n, 5 * n)    # F3, F4 -> GRU_P
        self.fc_meas = nn.Linear(2 * m, 5 * m)     # F1, F2 -> GRU_S
        self.gru_p = _GRUCell(5 * n, width * n * n)
        self.gru_s = _GRUCell(5 * m, width * m * m)
        self.fc_p = nn.Linear(width * n * n, n * n)
        self.fc_s = nn.Linear(width * m * m, m * m)
        self.register_parameter("h_p", nn.Parameter(torch.zeros(width * n * n)))
        self.register_parameter("h_s", nn.Parameter(torch.zeros(width * m * m)))
        for out, k in ((self.fc_p, n), (self.fc_s, m)):
            nn.init.zeros_(out.weight)
            with torch.no_grad():
                out.bias.copy_(gain**0.5 * torch.eye(k).flatten())

    def _start(self, b: int) -> list[torch.Tensor]:
        return [self.h_p.expand(b, -1), self.h_s.expand(b, -1)]

    def _gain(self, f1: torch.Tensor, f2: torch.Tensor, f3: torch.Tensor, f4: torch.Tensor,
              hidden: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        h_p, h_s = hidden
        p = self.gru_p(F.relu(self.fc_state(torch.cat([f3, f4], -1))), h_p)
        s = self.gru_s(F.relu(self.fc_meas(torch.cat([f1, f2], -1))), h_s)
        n, m = self.n_state, self.n_measured
        prior = self.fc_p(p).view(-1, n, n)
        s_inv = self.fc_s(s).view(-1, m, m)
        # K = P H^T S^-1, H = [I 0]: P's columns of the measured pose
        return (prior[:, :, :m] @ s_inv).flatten(1), [p, s]
