"""A learned noise model over a differentiable window EKF: the robust observer.

The network judges the measurement noise from the window and a Kalman filter on the
kinematic bicycle, run over the window, turns that judgement into an estimate. It is never
told alpha. What it learns:

- the measurement-noise sigmas R (one per channel): an MLP reads the log mean squares of
  the window's second differences (a statistic dominated by measurement noise, which the
  smooth motion hardly touches) and the mean speed, and outputs log sigma;
- a scale on the process noise Q (initialised at the noise preset's);
- the process model's error, with ``residual > 0`` or ``body="single_track"``
  (:mod:`lbo.models.motion`).

With a sixth input channel, ``fix`` (``in_features=6``), steps without a position fix get a
prediction-only step, the filter starts at the window's first fix, and the noise statistic is
the mean square of the fixes' residuals against dead reckoning from the previous fix (the
second differences need fixes at three consecutive steps).

With a receiver's features (``in_features=15``, :data:`lbo.models.receiver_window.FEATURES`),
each row updates with the channels it holds (:func:`lbo.models.update.masked_update`): a
position fix with or without a heading, the course over ground where it has no heading, and
the receiver's reported accuracies as the R of those channels in place of the noise model's;
the noise statistic counts full fixes only, as the recursive form's does. With ``gyro``, the
heading turns with a gyro's yaw rate ``r_m`` where the window holds one (the last reading
held), less a bias that is a fourth state, as the classical gyro EKF's does
(:mod:`lbo.filters.gyro`).

Trained end to end through the filter on the MSE of the final estimate, over windows of
alphas drawn from a wide range, it learns to be the EKF that alpha calls for."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, cast

import torch
from torch import nn

from lbo.core.checks import integer, number, require
from lbo.core.errors import LboError
from lbo.filters import gyro_noise
from lbo.models.channels import feature_channels, window_channels
from lbo.models.filter_step import FilterStep
from lbo.models.frame import check_sigmas, frame_model
from lbo.models.motion import ProcessModel, bicycle_step
from lbo.models.poses import wrap_heading
from lbo.models.receiver_window import FEATURES
from lbo.models.update import step_covariance, taken, turn_xy

EMPTY_STATISTIC = ("net", "learned")
"""R where the noise statistic is empty (under two fixes; a carried filter's start): ``net``,
the noise model at alpha = 1's statistic, which stands in; ``learned``, sigmas of their own
(``log_empty_sigma``). Asked there at every start, the net learns alpha = 1 as "nothing seen"."""
SIGMA_RATIO_MAX = 100.0
"""The largest measurement sigma the noise model gives, in units of its sigmas at alpha = 1:
far above the noise levels lbo trains on (alpha up to 6.5)."""


class WindowFilter(ProcessModel, FilterStep, nn.Module):
    """Window EKF on the kinematic bicycle with a learned noise model.

    Reads ``"frame"`` features in physical units (:mod:`lbo.models.features`): the window's
    measurements relative to the current one, rotated into its measured heading, and the
    inputs V (m/s) and delta (rad). Returns the estimate of the current state in the same
    frame (the ``"frame"`` target).

    Parameters
    ----------
    window : N, steps per window (>= 4).
    dt, wheelbase : the vehicle's sampling period (s) and wheelbase (m).
    process_sigma : (3,) sigma of the process noise per step (m, m, rad), the training preset's.
    measurement_sigma : (3,) measurement sigmas at alpha=1, the scale of the noise model.
    hidden : width of the noise model's two hidden layers.
    in_features : channels per step: 5, or 6 with the ``fix`` channel (missing fixes), or 15,
        a receiver's features (:data:`lbo.models.receiver_window.FEATURES`).
    residual : width of the process model's learned correction (two hidden layers); 0 keeps
        the kinematic bicycle.
    drift : also estimate a Gauss-Markov GNSS drift on x and y (two more filter states);
        its correlation time and its size relative to the white noise are learned.
    drift_tau : the drift's correlation time (s), held where given (a receiver's data sheet
        value); None learns it, from 10 s.
    body : the process model's body, ``"kinematic"`` (the bicycle, with the ``residual``
        correction if any) or ``"single_track"`` (lateral speed and yaw rate under learned
        tyre forces).
    body_lr : the single-track body's learning rate as a multiple of the optimiser's
        (:meth:`param_groups`): its seven constants each get a consistent gradient from every
        corner, and travel from the generic car to the one in the data in fewer steps.
    gyro : turn the heading with a gyro's yaw rate less a bias (a fourth state) where a
        receiver's window holds one (:meth:`_receiver_filter`); the gyro's white noise, the
        bias's start and its walk are learned, from :mod:`lbo.filters.gyro_noise`'s defaults.
        Needs a receiver's features and the kinematic bicycle without a residual.
    empty_statistic : R where the noise statistic holds nothing yet, one of
        :data:`EMPTY_STATISTIC`.
    input_terms : learn what undoes the input sensors' errors (a factor on the speed, an
        offset and a factor on the steering) and undo them before the process model reads
        the inputs (:meth:`learned_inputs`).
    body_rear : the single-track body's centre of gravity ahead of the rear axle (m), held
        where given (the car's geometry, weighed at its axles); None learns where it sits.
    """

    if TYPE_CHECKING:  # its buffers (or parameters) registered by name, for the type checker
        log_q0: torch.Tensor
        log_r0: torch.Tensor
        log_drift_tau: torch.Tensor
        log_drift_ratio: torch.Tensor
        log_empty_sigma: torch.Tensor
        log_gyro_sigma: torch.Tensor
        log_bias_sigma: torch.Tensor
        log_bias_walk: torch.Tensor

    def __init__(self, window: int, *, dt: float = 0.02, wheelbase: float = 2.7,
                 process_sigma: Sequence[float] = (0.0667, 0.0667, 0.00113),
                 measurement_sigma: Sequence[float] = (1.0, 1.0, 0.0174),
                 hidden: int = 32, in_features: int = 5, residual: int = 0,
                 drift: bool = False, body: str = "kinematic", body_lr: float = 1.0,
                 gyro: bool = False, empty_statistic: str = "net",
                 drift_tau: float | None = None, input_terms: bool = False,
                 body_rear: float | None = None) -> None:
        super().__init__()
        frame_model(self, window, in_features, dt, wheelbase, receiver=True)
        if empty_statistic not in EMPTY_STATISTIC:
            raise LboError(f"model.empty_statistic: expected one of {list(EMPTY_STATISTIC)}, "
                           f"got {empty_statistic!r}")
        self.empty_statistic = empty_statistic
        hidden = integer(hidden, "hidden", 1)
        q = torch.tensor(check_sigmas("process_sigma", process_sigma))
        r = torch.tensor(check_sigmas("measurement_sigma", measurement_sigma))
        self.register_buffer("log_q0", q.log())
        self.register_buffer("log_r0", r.log())
        # learned from alpha = 1's; without, the same values ride along unsaved (TorchScript)
        if empty_statistic == "learned":
            self.log_empty_sigma = nn.Parameter(r.log())
        else:
            self.register_buffer("log_empty_sigma", r.log(), persistent=False)
        # an attribute, not the global: TorchScript reads no module-level floats
        self.log_sigma_ratio_max = math.log(SIGMA_RATIO_MAX)
        self.log_q_scale = nn.Parameter(torch.zeros(3))
        # features: log mean square second difference per channel (in units of r0), log(1+V)
        # (with fixes, also the log of the mean gap between fixes)
        self.noise = nn.Sequential(nn.Linear(4 + self.fixes, hidden), nn.GELU(),
                                   nn.Linear(hidden, hidden),
                                   nn.GELU(), nn.Linear(hidden, 3))
        head = cast(nn.Linear, self.noise[-1])  # the Linear made just above
        nn.init.zeros_(head.weight)
        nn.init.zeros_(head.bias)
        if not isinstance(drift, bool):
            raise LboError(f"model.drift: expected true or false, got {drift!r}")
        if drift and self.receiver:
            raise LboError("model.drift: expected false for a window filter that reads a "
                           f"receiver (in_features={len(FEATURES)}), got True")
        self.drift = drift
        # the receiver's reported accuracies are in world axes: forward takes the anchor's
        # heading to turn them into the window's frame (lbo.models.net.WindowNet passes it)
        self.anchor_heading = self.receiver
        if drift_tau is not None:
            form = "null (learned) or a correlation time in seconds > 0 with model.drift=true"
            drift_tau = number(drift_tau, "model.drift_tau", low=0.0, low_open=True, form=form)
            require(drift, "model.drift_tau", form, drift_tau)
        # start at a 10 s correlation time (or the one given, held) and a drift of 0.3 of the
        # white sigma; without drift, the same values ride along unsaved, so TorchScript
        # compiles either filter
        for name, value in (("log_drift_tau", math.log((drift_tau or 10.0) / dt)),
                            ("log_drift_ratio", math.log(0.3))):
            if drift and not (name == "log_drift_tau" and drift_tau is not None):
                self.register_parameter(name, nn.Parameter(torch.tensor(value)))
            else:  # held: saved with the drift, so a checkpoint has the key either way
                self.register_buffer(name, torch.tensor(value), persistent=drift)
        self.build_process(residual, body, body_lr, input_terms, body_rear)
        self._build_gyro(gyro)
        # the filter's states (lbo.models.filter_step): the pose, and the gyro's bias or the drift;
        # their identity made once, not at every step of the loop
        self.states = 5 if drift else 4 if gyro else 3
        self.register_buffer("eye", torch.eye(self.states), persistent=False)

    def _build_gyro(self, gyro: bool) -> None:
        """Register the gyro's learned noise (``gyro``), checked in one line: log 1-sigmas of
        its white noise over a step (rad), of the bias at the window's start (rad/s) and of
        the bias's walk over a step (rad/s); without a gyro, the same values ride along
        unsaved, so TorchScript compiles either filter."""
        if not isinstance(gyro, bool):
            raise LboError(f"model.gyro: expected true or false, got {gyro!r}")
        if gyro and not (self.receiver and self.residual == 0 and not self.single_track):
            raise LboError("model.gyro: expected false unless the filter reads a receiver "
                           f"(in_features={len(FEATURES)}) on the kinematic bicycle without a "
                           f"residual, got True")
        self.gyro = gyro
        for name, value in (("log_gyro_sigma", math.log(gyro_noise.GYRO_SIGMA * self.dt)),
                            ("log_bias_sigma", math.log(gyro_noise.BIAS_SIGMA)),
                            ("log_bias_walk", math.log(gyro_noise.BIAS_WALK
                                                       * math.sqrt(self.dt)))):
            if gyro:
                self.register_parameter(name, nn.Parameter(torch.tensor(value)))
            else:
                self.register_buffer(name, torch.tensor(value), persistent=False)

    def _drift_noise(self, R: torch.Tensor, Q: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """The process noise of the filter with two more states, a Gauss-Markov GNSS drift b on
        x and y (``b' = phi b``, measured as ``m = pose + [b, 0]``), from the window's R
        (B, 3, 3) and the pose's Q (3, 3): (B, 5, 5), and the drift's stationary variance
        (B,). Its correlation time and its size relative to the white position noise are
        learned.

        The drift's mean is unobservable from positions alone; what the states buy is a filter
        that knows its position fixes' errors are correlated, and averages them no further
        than that allows."""
        white = (R[:, 0, 0] * R[:, 1, 1]) ** 0.25  # (B,) white position sigma
        var_b = (torch.exp(self.log_drift_ratio) * white) ** 2  # (B,) stationary variance
        pose = self.eye[:3]  # (3, 5) selector
        return pose.T @ Q @ pose + self.drift_walk(var_b), var_b

    def _fix_residuals(self, x: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Mean square residual of each fix against dead reckoning from the previous fix,
        halved (two fixes' noise), (B, 3), the log of the mean gap between fixes (B, 1), and
        whether the window had fewer than two fixes (B,): it gets the alpha=1 variance."""
        w = window_channels(x)
        fix = w.fix > 0.5
        dr = w.pose[:, 0]
        seen = fix[:, 0]
        gap = torch.zeros_like(w.V[:, 0])
        total = torch.zeros_like(dr)
        count = torch.zeros_like(gap)
        gaps = torch.zeros_like(count)
        for k in range(1, x.shape[1]):
            dr = bicycle_step(dr, w.V[:, k - 1], w.delta[:, k - 1], self.dt, self.wheelbase)
            gap = gap + 1
            f = fix[:, k]
            r = w.pose[:, k] - dr
            r = wrap_heading(r)
            use = (f & seen).to(x.dtype)
            total = total + use[:, None] * r ** 2
            count, gaps = count + use, gaps + use * gap
            dr = torch.where(f[:, None], w.pose[:, k], dr)
            gap = torch.where(f, torch.zeros_like(gap), gap)
            seen = seen | f
        some = count > 0
        ms = torch.where(some[:, None], total / (2 * count.clamp_min(1))[:, None],
                         torch.exp(2 * self.log_r0).expand_as(total))
        mean_gap = torch.where(some, gaps / count.clamp_min(1), torch.ones_like(gaps))
        return ms, torch.log(mean_gap)[:, None], ~some

    def measurement_sigma(self, x: torch.Tensor) -> torch.Tensor:
        """The noise model: (B, N, 5|6) features -> (B, 3) measurement sigmas."""
        w = window_channels(x)
        speed = torch.log1p(w.V.abs().mean(1, keepdim=True))
        empty = torch.zeros_like(speed[:, 0], dtype=torch.bool)  # differences: never empty
        if self.fixes:
            ms, log_gap, empty = self._fix_residuals(x)
        else:
            m = w.pose
            d2 = m[:, 2:] - 2 * m[:, 1:-1] + m[:, :-2]
            d2 = wrap_heading(d2)
            # second differences of i.i.d. noise of variance s^2 have variance 6 s^2
            ms = (d2 ** 2).mean(1) / 6.0
            log_gap = speed[:, :0]  # no column
        log_ratio = 0.5 * torch.log(ms + 1e-12) - self.log_r0  # about log alpha
        return self.noise_sigma(log_ratio, torch.cat([speed, log_gap], 1), empty)

    def noise_sigma(self, log_ratio: torch.Tensor, extra: torch.Tensor,
                    empty: torch.Tensor | None = None) -> torch.Tensor:
        """The noise model's (B, 3) measurement sigmas from the statistic's log ratio to the
        sigmas at alpha = 1 (B, 3) (about log alpha) and its other features (B, F) (log(1+V),
        and with fixes the log of the mean gap), in the window form and the recursive form.

        It starts from the plain moment estimate, ``exp(log_ratio) r0``, and is held inside
        [1e-6, :data:`SIGMA_RATIO_MAX` r0]: a filter carried from step to step reads the
        statistic where the window form never does (empty, at its first fix), and an
        unbounded output there overflowed P (float32) when it was trained carried. ``empty``
        (B,): where the statistic holds nothing (None: nowhere), which
        :attr:`empty_statistic` ``learned`` answers with its own sigmas."""
        log_sigma = log_ratio + self.log_r0 + self.noise(torch.cat([log_ratio, extra], 1))
        if empty is not None and self.empty_statistic == "learned":
            log_sigma = torch.where(empty[:, None], self.log_empty_sigma.expand_as(log_sigma),
                                    log_sigma)
        log_sigma = torch.minimum(log_sigma, self.log_r0 + self.log_sigma_ratio_max)
        return torch.exp(log_sigma).clamp_min(1e-6)

    def _receiver_filter(self, x: torch.Tensor, heading: torch.Tensor | None) -> torch.Tensor:
        """The window filter over a receiver's features x (B, N, 15) in the frame of their
        anchor, whose world heading is ``heading`` (B,) (None: 0, the world's axes) -> (B, 3)
        state in that frame; the anchor itself (0) where the window holds no row with a
        position and a heading to start at.

        Each row updates with the channels it holds: the position, the heading ``psi_m``, or
        the course over ground where it has none. Their R is the noise model's (read in the
        anchor's frame, on the full fixes alone) with the reported accuracies in its place (in
        world axes, :func:`step_covariance`); the filter starts at the first row that holds a
        position and a heading, with that row's R. With ``gyro``, the gyro's last reading
        turns the heading."""
        b, n = x.shape[0], x.shape[1]
        f = feature_channels(x)
        position, measured = f.has_fix > 0.5, f.has_heading > 0.5
        course = (f.has_course > 0.5) & ~measured
        held = torch.stack([position, position, measured | course], -1)  # (B, N, 3)
        meas = torch.cat([f.fix, torch.where(measured, f.heading, f.course)[..., None]], -1)
        full = (position & measured).to(x.dtype)[..., None]
        r = self.measurement_sigma(torch.cat([f.pose, f.V[..., None], f.delta[..., None], full],
                                             -1)) ** 2  # (B, 3), the anchor's frame
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        if heading is None:
            heading = torch.zeros_like(r[:, 0])
        c, s = torch.cos(heading)[:, None], torch.sin(heading)[:, None]
        world = turn_xy((r.unsqueeze(-1) * eye).unsqueeze(1).expand(b, n, 3, 3), c, s)
        sigma = f.sigma
        told = torch.stack([sigma[..., 0] > 0, sigma[..., 1] > 0, (sigma[..., 2] > 0) & measured],
                           -1)
        course_var = torch.where(f.course_sigma > 0, f.course_sigma ** 2, world[..., 2, 2])
        R = turn_xy(step_covariance(world, sigma, told, course_var, measured), c, -s)
        Q = torch.exp(2 * (self.log_q0 + self.log_q_scale)) * eye
        gyro: torch.Tensor | None = None
        if self.gyro:  # the bias's walk is the step's (predict)
            Q = nn.functional.pad(Q, (0, 1, 0, 1))
            gyro = torch.where(f.has_gyro > 0.5, f.gyro, torch.full_like(f.gyro, math.nan))
        z, started = self._window(meas, R, Q, f.V, f.delta, held=held.to(x.dtype), gyro=gyro)
        return torch.where(started[:, None], wrap_heading(z[:, :3]), torch.zeros_like(z[:, :3]))

    def _window(self, meas: torch.Tensor, R: torch.Tensor, Q: torch.Tensor, v: torch.Tensor,
                delta: torch.Tensor, fix: torch.Tensor | None = None,
                held: torch.Tensor | None = None, gyro: torch.Tensor | None = None,
                drift_var: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The window form: the filter's one step (:mod:`lbo.models.filter_step`) over the
        rows of a window, from its first. Measurements meas (B, N, 3) of covariance R, the
        window's (B, 3, 3) or each row's (B, N, 3, 3); the process noise Q ((n, n) or
        (B, n, n)); the inputs v and delta (B, N), row k - 1's moving the filter to row k.

        Which rows update: every row, with every channel (the paper's windows); with ``fix``
        (B, N) bool, the rows that hold a fix, the others a prediction only; with ``held``
        (B, N, 3) (1 or 0), the channels each row holds (a receiver's, Joseph's update). The
        filter starts at the window's first row and again at its first row that holds a
        position and a heading, if later (a receiver's window starts its body there too, as
        the recursive form does). ``gyro`` (B, N): the gyro's readings (NaN: none), the last
        held turning the heading (``model.gyro``); ``drift_var`` (B,): the drift's stationary
        variance (``model.drift``). Returns z (B, n) at the last row and whether the filter
        started (B,). (Its settings are not keyword-only: TorchScript compiles none.)"""
        each_row = R.dim() == 4
        z, P = self.start(meas[:, 0], R[:, 0] if each_row else R, drift_var)
        body = self.body_start(v[:, 0], delta[:, 0])
        can_start, updates = fix, fix
        if held is not None:
            can_start, updates = (held[..., 0] > 0.5) & (held[..., 2] > 0.5), (held > 0.5).any(-1)
        started = torch.ones_like(v[:, 0], dtype=torch.bool) if can_start is None \
            else can_start[:, 0]
        reading = torch.full_like(v[:, 0], math.nan)  # the gyro's last reading (rad/s)
        for k in range(1, meas.shape[1]):
            if gyro is not None:
                reading = torch.where(gyro[:, k - 1] == gyro[:, k - 1], gyro[:, k - 1], reading)
            prior = self.predict(z, P, v[:, k - 1], delta[:, k - 1], body, Q, reading)
            R_k = R[:, k] if each_row else R
            z_upd, P_upd = self.correct(prior.z, prior.P, meas[:, k], R_k,
                                        None if held is None else held[:, k])
            body = prior.body
            if can_start is not None and updates is not None:
                first = can_start[:, k] & ~started
                z, P = taken(first, updates[:, k] & started,
                             self.start(meas[:, k], R_k, drift_var), (z_upd, P_upd),
                             (prior.z, prior.P))
                if held is not None:
                    body = torch.where(first[:, None], self.body_start(v[:, k], delta[:, k]),
                                       body)
                started = started | first
            else:
                z, P = z_upd, P_upd
        return z, started

    def forward(self, x: torch.Tensor, heading: torch.Tensor | None = None) -> torch.Tensor:
        """(B, N, 5|6|15) features -> (B, 3) state in the anchor's (current measurement's)
        frame. ``heading`` (B,): the anchor's heading in world axes, read with a receiver's
        features only (:meth:`_receiver_filter`)."""
        if self.receiver:
            return self._receiver_filter(x, heading)
        r = self.measurement_sigma(x) ** 2  # (B, 3)
        q = torch.exp(2 * (self.log_q0 + self.log_q_scale))  # (3,)
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        R = r.unsqueeze(-1) * eye  # diagonal matrices, written so that ONNX exports them
        Q = q * eye
        drift_var: torch.Tensor | None = None
        if self.drift:
            Q, drift_var = self._drift_noise(R, Q)
        w = window_channels(x)
        z, _ = self._window(w.pose, R, Q, w.V, w.delta,
                            fix=w.fix > 0.5 if self.fixes else None, drift_var=drift_var)
        return wrap_heading(z[:, :3])
