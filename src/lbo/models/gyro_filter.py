"""The gyro EKF with learned noise: a differentiable twin of :class:`lbo.filters.gyro.GyroStepper`.

:class:`GyroFilter` steps the same model and the same update as the NumPy stepper (a fix's
reported accuracy as R, the course over ground, the zero-rate update at standstill; the
Joseph form with the channels each row holds) in torch, so that a loss on its estimates
reaches the seven numbers of :class:`lbo.filters.gyro_noise.GyroNoise`, held here as their logs
(:data:`UNITS`).
It runs from a state the NumPy stepper gives (after the heading is known: the course start is
the stepper's), over G segments at once; the noise it learns goes back into the NumPy
stepper, which is what observes (tested equal to 1e-9).

It reads single-antenna logs: fixes without a heading. A noise that carries the fixes' drift
(:attr:`GyroNoise.drift`) adds its two states, as the NumPy stepper does, and learns its size
and correlation time with the rest: a likelihood that can tell the fixes' slow error from the
car's motion.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import nn

from lbo.filters import gyro as gyro_np
from lbo.filters import measure
from lbo.filters.gyro_noise import GyroNoise
from lbo.models.poses import wrap_angle_torch
from lbo.models.update import joseph

_NAMES = tuple(f.name for f in dataclasses.fields(GyroNoise))
UNITS = {"speed_scale": 0.02, "gyro_scale": 0.02}
"""Each noise is learned as its log over its unit (1 where not named): a step of the optimiser
moves a scale of the inputs by a fiftieth of what it moves a noise, for a speed off by 1% is a
large error and a noise off by 10% a small one (Adam's steps are about lr in these units)."""
_FIX = (0, 1)
"""The channels of a fix (x_m, y_m) among the filter's four (then the course, the gyro at
standstill)."""


class Segments(NamedTuple):
    """G stretches of a log, each started from the NumPy stepper's state (float64 tensors).

    x0 : (G, n) ``[x, y, psi, b]`` (n = 4; then the fixes' drift ``[dx, dy]``, n = 6) and
        P0 : (G, n, n) at each segment's first step.
    fix : (G, T, 2) ``x_m, y_m`` (NaN: no fix).
    accuracy : (G, T, 2) reported ``sx_m, sy_m`` (NaN: the filter's R).
    course : (G, T) direction of the GNSS velocity (plus pi reversing; NaN: no velocity).
    speed : (G, T) its magnitude (m/s); sv : (G, T) its sigma (m/s, the default filled in).
    u : (G, T, 2) ``[V, r_m]``.
    truth : (G, T, 3) ``[x, y, psi]``.
    """

    x0: torch.Tensor
    P0: torch.Tensor
    fix: torch.Tensor
    accuracy: torch.Tensor
    course: torch.Tensor
    speed: torch.Tensor
    sv: torch.Tensor
    u: torch.Tensor
    truth: torch.Tensor


class GyroFilter(nn.Module):
    """The gyro EKF over :class:`Segments`, its noise learned.

    noise : the starting noise (with the fixes' drift, n = 6 states, else 4); dt : the
    sampling period (s); R : (3, 3) the filter's R where a fix reports no accuracy (its x, y
    block is used).
    """

    if TYPE_CHECKING:  # buffers registered by name, for the type checker
        R2: torch.Tensor
        H: torch.Tensor

    def __init__(self, noise: GyroNoise, dt: float, R: torch.Tensor) -> None:
        super().__init__()
        self.dt = float(dt)
        held = {k: getattr(noise, k) for k in _NAMES if getattr(noise, k) is not None}
        self.log = nn.ParameterDict({
            k: nn.Parameter(torch.tensor(math.log(v) / UNITS.get(k, 1.0), dtype=torch.float64))
            for k, v in held.items()})
        self.n = 6 if noise.drift is not None else 4
        self.register_buffer("R2", torch.as_tensor(R, dtype=torch.float64)[:2, :2].clone())
        H = torch.zeros(4, self.n, dtype=torch.float64)  # x_m, y_m, course, standstill gyro
        H[0, 0] = H[1, 1] = H[2, 2] = H[3, 3] = 1.0
        if self.n == 6:
            H[0, 4] = H[1, 5] = 1.0  # a fix measures the position plus its drift
        self.register_buffer("H", H)

    def noise(self) -> GyroNoise:
        """The current noise."""
        return GyroNoise(**{k: float(v.detach()) for k, v in self._values().items()})

    def _values(self) -> dict[str, torch.Tensor]:
        """Each noise it holds, from its parameter (:data:`UNITS`)."""
        return {k: torch.exp(v * UNITS.get(k, 1.0)) for k, v in self.log.items()}

    def forward(self, seg: Segments) -> torch.Tensor:
        """Estimates (G, T, 3) ``[x, y, psi]``: step 0 is ``x0``, step k predicted with
        ``u[:, k - 1]`` and updated with row k, as :func:`lbo.filters.stepper.run_stepper`."""
        return self.run(seg)[0]

    def run(self, seg: Segments) -> tuple[torch.Tensor, torch.Tensor]:
        """Estimates (G, T, 3), as :meth:`forward`, and each step's negative log-likelihood
        (G, T) of what it measured under the filter's own prediction (:func:`scored_update`;
        0 at step 0 and where it measured nothing): what the filter is fitted by where a log
        has no truth."""
        x, _, nll = self.states(seg)
        return x[..., :3], nll

    def ahead(self, seg: Segments, steps: int,
              states: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """The negative log-likelihood (F,) of each fix ``steps`` rows after a step of the
        same segment, under the filter's prediction from that step's estimate with no
        measurement between (dead reckoning on the speed and the gyro): how well the noise
        predicts where the car will be, which a heading error or a trust in the course it
        does not deserve spoils more than it spoils the next fix. F: the fixes so
        predicted (those ``steps`` or more rows into their segment). ``states``: the
        segments' states and covariances as :meth:`states` gave them (None: run it)."""
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        x, P = self.states(seg)[:2] if states is None else states
        g, t = seg.fix.shape[:2]
        held = torch.isfinite(seg.fix).all(-1)
        held[:, :steps] = False
        gi, ti = torch.nonzero(held, as_tuple=True)  # the fixes predicted, at row ti
        start = ti - steps
        xs, Ps = x[gi, start], P[gi, start]
        Q, phi = self._Q(), self._phi()
        drive, F = self._steps(self._inputs(seg.u), phi)
        for j in range(steps):
            xs, Ps = self._predict(xs, Ps, drive[gi, start + j], Q, phi, F[gi, start + j])
        Hf = self.H[list(_FIX)]
        S = Hf @ Ps @ Hf.T + self._fix_R(seg.accuracy[gi, ti])
        y = seg.fix[gi, ti] - xs @ Hf.T
        mahalanobis = (y[:, None, :] @ torch.linalg.solve(S, y[:, :, None]))[:, 0, 0]
        return 0.5 * (mahalanobis + torch.logdet(S) + 2 * math.log(2 * math.pi))

    def _fix_R(self, accuracy: torch.Tensor) -> torch.Tensor:
        """(..., 2, 2) the fixes' R from their reported accuracy (..., 2) (NaN: none): a
        reported one, times the learned scale, replaces the filter's variance and drops its
        correlation (:func:`lbo.filters.measure.step_cov`)."""
        told = torch.isfinite(accuracy)
        acc = torch.nan_to_num(accuracy, nan=1.0) * self._values()["accuracy_scale"]
        either = told[..., :, None] | told[..., None, :]
        R2 = torch.where(either, torch.zeros((), dtype=acc.dtype), self.R2)
        return R2 + torch.diag_embed(torch.where(told, acc**2, torch.zeros_like(acc)))

    def _inputs(self, u: torch.Tensor) -> torch.Tensor:
        """u (..., 2) ``[V, r_m]`` as the model reads them: times the learned scales of the
        speed and the gyro, where the noise holds them (:attr:`GyroNoise.speed_scale`)."""
        if "speed_scale" not in self.log:
            return u
        p = self._values()
        return u * torch.stack([p["speed_scale"], p["gyro_scale"]])

    def _phi(self) -> torch.Tensor:
        """The drift's factor over one step, ``exp(-dt / tau)`` (1 without a drift)."""
        if self.n == 4:
            return torch.ones((), dtype=torch.float64)
        return torch.exp(-self.dt / self._values()["drift_tau"])

    def _Q(self) -> torch.Tensor:
        """(n, n) the process noise of one step (the drift's that of its stationary
        first-order Gauss-Markov process, as :class:`lbo.filters.gyro.GyroStepper`'s)."""
        p = self._values()
        q = [p["q_position"] ** 2, p["q_position"] ** 2,
             p["q_heading"] ** 2 + (p["gyro_sigma"] * self.dt) ** 2, p["bias_walk"] ** 2 * self.dt]
        if self.n == 6:
            q += [p["drift_sigma"] ** 2 * (1.0 - self._phi() ** 2)] * 2
        return torch.diag(torch.stack(q))

    def _steps(self, u: torch.Tensor, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What the model takes from inputs u (..., 2) ``[V, r_m]``, whatever the state:
        ``[V, r_m]`` with the gyro's rate 0 at a standstill (the turn is held there), and
        (..., n, n) the Jacobian's part that the state does not move (the identity, the
        bias's pull on the heading, -dt where the car moves, and the drift's decay phi).
        :meth:`_predict` adds what depends on the state."""
        n, dt = self.n, self.dt
        still = u[..., 0].abs() < gyro_np.STILL_SPEED
        zero = torch.zeros((), dtype=u.dtype)
        F = torch.eye(n, dtype=u.dtype).expand(*u.shape[:-1], n, n).clone()
        F[..., 2, 3] = torch.where(still, zero, torch.full((), -dt, dtype=u.dtype))
        if n == 6:
            F[..., 4, 4] = F[..., 5, 5] = phi
        return torch.stack([u[..., 0], torch.where(still, zero, u[..., 1])], -1), F

    def _predict(self, x: torch.Tensor, P: torch.Tensor, drive: torch.Tensor, Q: torch.Tensor,
                 phi: torch.Tensor, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One step of the model: x (B, n), P (B, n, n) on drive (B, 2) and F (B, n, n) as
        :meth:`_steps` gives them: the heading turns by the gyro less its bias, held at a
        standstill (the gyro then measures its bias: F's bias term is 0 there); the drift
        decays by phi (:meth:`_phi`, computed once per run)."""
        dt = self.dt
        v = drive[:, 0]
        psi, bias = x[:, 2], x[:, 3]
        c, s = torch.cos(psi), torch.sin(psi)
        x = torch.cat([torch.stack([x[:, 0] + v * c * dt, x[:, 1] + v * s * dt,
                                    psi + drive[:, 1] * dt + F[:, 2, 3] * bias, bias], -1),
                       x[:, 4:] * phi], -1)
        F = F.clone()
        F[:, 0, 2] = -v * s * dt
        F[:, 1, 2] = v * c * dt
        return x, F @ P @ F.transpose(-1, -2) + Q

    def states(self, seg: Segments) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The filter over the segments: states (G, T, n), covariances (G, T, n, n) and each
        step's negative log-likelihood (G, T), as :meth:`run` says."""
        p = self._values()
        g, t = seg.fix.shape[:2]
        dtype = seg.x0.dtype
        Q, H, phi = self._Q(), self.H, self._phi()  # once: the same at every step
        u = self._inputs(seg.u)
        drive, F = self._steps(u, phi)
        # the velocity's course, as lbo.filters.measure.course_over_ground holds it
        speed = torch.nan_to_num(seg.speed, nan=0.0)
        course_held = ((speed >= measure.COURSE_MIN_SPEED)
                       & (speed >= measure.COURSE_MIN_SNR * seg.sv) & torch.isfinite(seg.course))
        safe = torch.where(course_held, speed, torch.ones_like(speed))
        sv = p["velocity_scale"] * seg.sv  # trusted less or more; held where it is reported
        course_var = (sv**2 + (p["course_lever"] * u[..., 1]) ** 2) / safe**2
        # what every step measures, how well, and which channels it holds, for all steps at
        # once: the loop keeps only what the state moves
        R = torch.zeros((g, t, 4, 4), dtype=dtype)
        R[..., :2, :2] = self._fix_R(seg.accuracy)
        R[..., 2, 2] = torch.where(course_held, course_var, torch.ones_like(course_var))
        R[..., 3, 3] = p["gyro_sigma"] ** 2
        fix_held = torch.isfinite(seg.fix)
        # step k is predicted on the inputs of row k - 1, and its standstill gyro update
        # reads them too (row 0 is the start: its slot is never read)
        before = torch.cat([u[:, :1], u[:, :-1]], 1)
        still = before[..., 0].abs() < gyro_np.STILL_SPEED
        held = torch.stack([fix_held[..., 0], fix_held[..., 1], course_held, still], -1)
        measured = torch.stack([*torch.nan_to_num(seg.fix, nan=0.0).unbind(-1),
                                torch.nan_to_num(seg.course, nan=0.0), before[..., 1]], -1)
        Hm, Rm, y_held, m = _masked(H, R, held)
        angle = torch.tensor([False, False, True, False])  # the course's innovation wraps
        # each step's slice taken by one unbind: indexing a tensor that needs a gradient
        # step by step would have its backward fill a whole (G, T, ...) zero tensor per step
        drive_k, F_k, measured_k, y_held_k, Hm_k, Rm_k, m_k = (
            a.unbind(1) for a in (drive, F, measured, y_held, Hm, Rm, m))
        x, P = seg.x0, seg.P0
        xs, Ps, nll = [x], [P], [torch.zeros(g, dtype=dtype)]
        for k in range(1, t):
            x, P = self._predict(x, P, drive_k[k - 1], Q, phi, F_k[k - 1])
            y = measured_k[k] - x @ H.T  # the fixes drifted, the heading, the bias
            y = torch.where(angle, wrap_angle_torch(y), y)
            x, P, step_nll = _scored(x, P, y * y_held_k[k], Hm_k[k], Rm_k[k], m_k[k])
            xs.append(x)
            Ps.append(P)
            nll.append(step_nll)
        return torch.stack(xs, 1), torch.stack(Ps, 1), torch.stack(nll, 1)


def _masked(H: torch.Tensor, R: torch.Tensor, held: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A measurement model cut to the channels held, for any leading dims (...): H (p, n),
    R (..., p, p), held (..., p) bool. Returns H (..., p, n) with the rows not held zero, R
    (..., p, p) with the identity where a channel is not held, the innovation's mask
    (..., p) as 0 or 1, and the number of channels held (...): a channel not held then has
    y = 0 and S = 1, and adds nothing to the update or the likelihood."""
    eye_p = torch.eye(held.shape[-1], dtype=R.dtype)
    mask = held.to(R.dtype)
    both = held[..., :, None] & held[..., None, :]
    return H * mask[..., None], torch.where(both, R, eye_p), mask, held.sum(-1)


def _scored(x: torch.Tensor, P: torch.Tensor, y: torch.Tensor, H: torch.Tensor,
            R: torch.Tensor, m: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The update (:func:`lbo.models.update.joseph`) of x (G, n), P (G, n, n) by innovations
    y (G, p) under H (G, p, n) and R (G, p, p) already cut to the m (G,) channels held
    (:func:`_masked`), and the innovation's negative log-likelihood (G,): S is factored once
    (Cholesky: S is symmetric positive definite) for the gain, the Mahalanobis distance and
    log det S."""
    PHt = P @ H.transpose(-1, -2)
    S = H @ PHt + R
    L = torch.linalg.cholesky(S)
    K = torch.cholesky_solve(PHt.transpose(-1, -2), L).transpose(-1, -2)
    x, P = joseph(x, P, PHt, K, y, R, H)
    white = torch.linalg.solve_triangular(L, y[..., None], upper=False)[..., 0]
    log_det = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    nll = 0.5 * ((white**2).sum(-1) + log_det + m * math.log(2 * math.pi))
    return x, P, nll


def scored_update(x: torch.Tensor, P: torch.Tensor, y: torch.Tensor, H: torch.Tensor,
                  R: torch.Tensor, held: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The update of the held channels (every torch filter's, :func:`lbo.models.update.joseph`,
    its gain by Cholesky) with the likelihood of its innovation, differentiable: x (G, n),
    P (G, n, n), y (G, p), H (p, n), R (G, p, p), held (G, p) bool.

    Returns the updated x (G, n) and P (G, n, n), and the innovation's negative
    log-likelihood (G,) under its covariance S, ``(y^T S^-1 y + log det S + m log 2 pi) / 2``
    over the m channels held (0 where none is: a channel not held has y = 0 and S = 1)."""
    Hm, Rm, mask, m = _masked(H, R, held)
    return _scored(x, P, y * mask, Hm, Rm, m)
