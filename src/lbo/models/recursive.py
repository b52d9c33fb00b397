"""The robust observer in recursive form: one sample in, one estimate out, at a constant cost.

:class:`~lbo.models.filternet.WindowFilter` runs its EKF over a whole window of N samples for
every estimate, from a cold start at the window's first sample. :class:`RecursiveFilter` is
the same filter, with the same learned parts, run the way a Kalman filter runs in a car:

- the filter state ``(z, P)`` carries from step to step, so each estimate costs one prediction
  and one update, whatever N is, and draws on everything seen since the start;
- the noise statistic the learned noise model reads (the mean square of the measurements'
  second differences, or of the fixes' residuals against dead reckoning when fixes are
  missing, and the mean speed) is a running sum over ring buffers of the last N steps.

The window form reads its window in the frame of its latest fix. The recursive form keeps the
sums of the entries' outer products in world axes, turns them into that frame at every step
(exactly what the window form sees) and the noise model's sigmas back into a world-axes R; so
the estimates move and turn with the log, as the window form's do.

Everything lives in explicit state tensors (:meth:`RecursiveFilter.initial_state`), so the
step exports to TorchScript and ONNX as a pure function ``(m, u, *state) -> (pose, cov,
*state)``, in float64 (kilometres of coordinates; running sums over hours). Conventions as
:mod:`lbo.filters.start`'s: ``u_k`` moves ``z_k`` to ``z_{k+1}``; a measurement of NaN is a
step without a fix (a prediction only, for a filter trained with the ``fix`` channel). The
filter starts at the first fix, with P = 6.5^2 R (:data:`START_SCALE`).

A receiver's rows (``(B, 8)``, :data:`lbo.filters.measure.CHANNELS`) are taken channel by
channel, as the classical filters take them: a fix with or without ``psi_m``, the course over
ground as the heading where a row has no ``psi_m``, the reported accuracy (and the course's
sigma) as those channels' R (a masked Kalman update). The noise model's statistic counts full
fixes only, as it was trained. Before the first row with a position and a heading the
estimate is NaN. A filter trained with a gyro (``model.gyro``) takes a third input, the gyro's
last reading ``r_m`` (NaN before the first), and carries the gyro's bias as a fourth state.
"""

from __future__ import annotations

import copy
import math
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from lbo.filters.kalman import coast_covariance, compose_covariance
from lbo.filters.measure import Row, row_channels
from lbo.models.filternet import WindowFilter
from lbo.models.motion import bicycle_step
from lbo.models.poses import wrap_heading
from lbo.models.update import mm, step_covariance

STATE_NAMES = ("z", "P", "body", "u_prev", "last", "dead_reckoning", "gap", "heading",
               "ring", "sums", "speeds", "speed_sum", "k", "started")
"""The state tensors of a batch of B filters, in order (:meth:`RecursiveFilter.initial_state`)."""
START_SCALE = 6.5**2
"""P at the first fix, in units of the R the noise model gives then: its statistic holds nothing
yet, so R is alpha = 1's, and the start must be as unsure as the noisiest level trained on."""
ENTRY = ("xx", "yy", "xy", "psi", "counted", "gap")
"""The channels of one entry of the statistic's ring (world axes)."""


class _Single(nn.Module):
    """A net run in float32 inside the float64 filter, as trained (ONNX has no float64 Erf)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net.float()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.float()).to(x.dtype)


class RecursiveFilter(nn.Module):
    """A trained :class:`WindowFilter`, stepped one sample at a time (float64).

    Parameters
    ----------
    net : the window filter whose learned parts it runs: copied into float64, or with
        ``shared`` its own, in its own dtype (to train it carried, :mod:`lbo.models.carried`).

    Attributes
    ----------
    window_filter : its float64 copy of the window filter (the nets inside run in float32).
    window : N, the steps the noise statistic runs over.
    n : filter states, 3 ``[x, y, psi]``, 4 with the gyro's bias ``b`` or 5 with the GNSS
        drift ``[b_x, b_y]``.
    fixes : whether steps without a fix are taken (the net has the ``fix`` channel).
    inputs : the columns of u: ``V, delta``, and the gyro's last reading ``r_m`` (NaN: none
        yet) for a filter trained with a gyro.
    keep_prior : whether :meth:`forward` keeps each step's prior and cross covariance in
        ``last_prior`` (what :func:`lbo.filters.smoother.rts` needs); set by :meth:`run`.
    """

    def __init__(self, net: WindowFilter, shared: bool = False) -> None:
        super().__init__()
        if shared:
            self.window_filter = net
        else:
            nets = {name: _Single(copy.deepcopy(getattr(net, name)))
                    for name in ("noise", "process")
                    if not isinstance(getattr(net, name), nn.Identity)}
            self.window_filter = copy.deepcopy(net).double().eval()
            for name, wrapped in nets.items():
                setattr(self.window_filter, name, wrapped.eval())
        self.window = int(net.window)
        self.fixes = bool(net.fixes)
        self.keep_prior = False
        self.gyro = bool(net.gyro)
        self.n = net.states
        self.inputs = ("V", "delta", "r_m") if self.gyro else ("V", "delta")
        # slots of the statistic's ring: N-2 second differences, or N-1 fix residuals
        self.slots = self.window - 1 if self.fixes else self.window - 2

    def initial_state(self, batch: int = 1, device: torch.device | str = "cpu",
                      dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, ...]:
        """The state of ``batch`` filters that have seen nothing, in the order of
        :data:`STATE_NAMES`:

        z (B, n), P (B, n, n), body (B, 2) the process model's carried ``[v_y, r]``
        (:meth:`lbo.models.motion.ProcessModel.motion`), u_prev (B, I) the last
        input (:attr:`inputs`), last (B, 2, 3) the last two measurements, dead_reckoning
        (B, 3) the pose carried from the last fix, gap (B,) steps since it, heading (B,) the
        last fix's measured heading, ring (B, S, 6) the statistic's last S entries
        (:data:`ENTRY`: the squares and cross product of the x and y parts, the square of the
        heading part, whether the entry counts, and its gap), sums (B, 6) their sum, speeds
        (B, N) the last N speeds, speed_sum (B,), k (1,) steps taken, started (B,) 1 once a
        fix was seen.
        """
        def zeros(*shape: int) -> torch.Tensor:
            return torch.zeros(*shape, dtype=dtype, device=device)

        b, n = batch, self.n
        return (zeros(b, n), zeros(b, n, n), zeros(b, 2), zeros(b, len(self.inputs)),
                zeros(b, 2, 3), zeros(b, 3), zeros(b), zeros(b),
                zeros(b, self.slots, len(ENTRY)), zeros(b, len(ENTRY)), zeros(b, self.window),
                zeros(b), zeros(1), zeros(b))

    def _noise(self, sums: torch.Tensor, speed: torch.Tensor, heading: torch.Tensor
               ) -> torch.Tensor:
        """(B, 3, 3) measurement covariance R in world axes from the running sums (B, 6), the
        mean speed (B,) and the latest fix's heading (B,): the net's noise model on the
        statistic of the last N steps in that fix's frame (alpha = 1 before any)."""
        fo = self.window_filter
        count = sums[:, 4]
        some = count > 0
        c, s = torch.cos(heading), torch.sin(heading)
        cc, ss, cs = c * c, s * s, c * s
        xx, yy, xy, pp = (sums[:, :4] / count.clamp_min(1)[:, None]).unbind(1)
        # the second moments in the frame turned by the heading: along and across it; held at
        # 0 and above, as squares are: turned from world-axis sums, a residual that lies
        # along the heading leaves a rounding error across it, which may be negative
        along = (cc * xx + 2 * cs * xy + ss * yy).clamp_min(0.0)
        across = (ss * xx - 2 * cs * xy + cc * yy).clamp_min(0.0)
        ms = torch.where(some[:, None], torch.stack([along, across, pp], 1),
                         torch.exp(2 * fo.log_r0).expand(sums.shape[0], 3))
        log_ratio = 0.5 * torch.log(ms + 1e-12) - fo.log_r0
        extra = [torch.log1p(speed)[:, None]]
        if self.fixes:
            mean_gap = torch.where(some, sums[:, 5] / count.clamp_min(1), torch.ones_like(count))
            extra.append(torch.log(mean_gap)[:, None])
        va, vc, vp = (fo.noise_sigma(log_ratio, torch.cat(extra, 1), ~some) ** 2).unbind(1)
        # back to world axes: R_xy = rot diag(va, vc) rot^T
        rxx, ryy, rxy = cc * va + ss * vc, ss * va + cc * vc, cs * (va - vc)
        zero = torch.zeros_like(va)
        return torch.stack([rxx, rxy, zero, rxy, ryy, zero, zero, zero, vp], -1).view(-1, 3, 3)

    @staticmethod
    def _step_cov(R: torch.Tensor, c: Row, held: Row, measured: torch.Tensor) -> torch.Tensor:
        """The step's R (B, 3, 3) of ``[x_m, y_m, heading]``: the noise model's ``R``, with the
        variance of each channel the row ``c`` reports an accuracy for (``held``: which of its
        entries are not NaN) replaced by its square (:func:`step_covariance`), and the
        heading's the course's where ``measured`` (B,) is False (no ``psi_m``)."""
        told, sig = held.sigma, torch.where(held.sigma, c.sigma, torch.zeros_like(c.sigma))
        # a heading the row does not hold gets a variance of 1: finite, and masked out
        course = torch.where(held.course_sigma, c.course_sigma, torch.ones_like(c.course_sigma))
        return step_covariance(R, sig, told, course * course, measured)

    def _drift_variance(self, R: torch.Tensor) -> torch.Tensor:
        """(B,) the drift's stationary variance from the step's R (B, 3, 3): the learned
        ratio squared times the white position variance, sqrt(det) of R's xy block (free of
        the heading R is turned by). The determinant is held above 1e-30: a nearly singular
        block (the statistic's first entry, along the heading) rounds it below zero."""
        det = (R[:, 0, 0] * R[:, 1, 1] - R[:, 0, 1] ** 2).clamp_min(1e-30)
        return torch.exp(2 * self.window_filter.log_drift_ratio) * det.sqrt()

    def _process_cov(self, heading: torch.Tensor) -> torch.Tensor:
        """(B, n, n) the learned Q at the latest fix's headings (B,): its x and y are along
        and across that heading, as R's."""
        q = torch.exp(2 * (self.window_filter.log_q0 + self.window_filter.log_q_scale))
        c, sn = torch.cos(heading), torch.sin(heading)
        cc, ss = c * c, sn * sn
        qxx, qyy, qxy = cc * q[0] + ss * q[1], ss * q[0] + cc * q[1], c * sn * (q[0] - q[1])
        zero = torch.zeros_like(qxx)
        Q = torch.stack([qxx, qxy, zero, qxy, qyy, zero, zero, zero, q[2].expand_as(qxx)],
                        -1).view(-1, 3, 3)
        return Q if self.n == 3 else nn.functional.pad(Q, (0, self.n - 3, 0, self.n - 3))

    @property
    def coasts(self) -> bool:
        """Whether :meth:`coast` takes this filter's rows without a measurement: the
        kinematic bicycle without a learned correction, trained with missing fixes, its
        states the pose (the robust observer of ``experiment=robust``) or the pose and the
        gyro's bias."""
        fo = self.window_filter
        return (self.n == 3 or self.gyro) and self.fixes and not fo.single_track \
            and fo.residual == 0

    @property
    def coast_limit(self) -> int:
        """The most rows one :meth:`coast` takes: its ring slots, each written once."""
        return min(self.slots, self.window)

    def coast(self, u: torch.Tensor, *state: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """K rows without any measurement at once (a prediction each), for one started
        filter (B = 1, :attr:`coasts`): their inputs u (K, I) -> poses (K, 3) (psi wrapped),
        covariances (K, 3, 3) and the new state; the numbers of K calls of :meth:`forward`
        with NaN rows (to rounding: tested to 1e-12). A log's fixes come at 1 to 10 Hz and
        its inputs at 50 Hz, so most rows are such: each costs a few operations here, where
        :meth:`forward` runs the whole step (the noise model, the statistic, the update)."""
        (z, P, body, u_prev, last, dr, gap, heading, ring, sums, speeds, speed_sum, k,
         started) = state
        fo = self.window_filter
        steps = len(u)
        if not (self.coasts and len(z) == 1 and 0 < steps <= self.coast_limit):
            raise ValueError("coast takes 1 to coast_limit rows of one kinematic filter")
        before = torch.cat([u_prev, u[:-1]])  # row j predicts with the input of row j - 1
        v, delta = before[:, 0], before[:, 1]
        along, across, rate, bodies = fo.motion(v, delta, body.expand(steps, 2))
        turn = rate * fo.dt
        heading_turn = turn  # the pose's turn
        if self.gyro:  # the gyro's last reading less the bias, none at rest (forward's)
            gyro, c, seen = fo.gyro_turn(before[:, 2], v, z[0, 3].expand(steps))
            heading_turn = torch.where(seen, gyro, turn)

        def roll(start: torch.Tensor, turn: torch.Tensor) -> tuple[torch.Tensor, ...]:
            # the motion from ``start`` (1, 3): forward adds one step's increment at a time,
            # and a cumulative sum adds them in the same order
            psi = torch.cumsum(torch.cat([start[:, 2], turn]), 0)
            c, sn = torch.cos(psi[:-1]), torch.sin(psi[:-1])
            dx, dy = along * c - across * sn, along * sn + across * c
            x = torch.cumsum(torch.cat([start[:, 0], dx * fo.dt]), 0)
            y = torch.cumsum(torch.cat([start[:, 1], dy * fo.dt]), 0)
            return torch.stack([x[1:], y[1:], psi[1:]], -1), dx, dy

        poses, dx, dy = roll(z, heading_turn)
        dead = roll(dr, turn)[0]
        eye = torch.eye(self.n, dtype=z.dtype, device=z.device)
        Q = self._process_cov(heading)
        if self.gyro:
            # forward's Jacobians I + a_j e3^T + c_j e3 e4^T and noises, composed by a scan
            F = eye.repeat(steps, 1, 1)
            F[:, 0, 2], F[:, 1, 2], F[:, 2, 3] = -dy * fo.dt, dx * fo.dt, c
            Qs = Q.repeat(steps, 1, 1)
            Qs[:, 2, 2] = torch.where(seen, torch.exp(2 * fo.log_gyro_sigma), Q[0, 2, 2])
            Qs[:, 3, 3] = torch.exp(2 * fo.log_bias_walk)
            A, B = compose_covariance(F, Qs)
            full = A @ P @ A.transpose(1, 2) + B
            covs = 0.5 * (full + full.transpose(1, 2))
            poses = torch.cat([poses, z[:, 3:].expand(steps, 1)], 1)
        else:  # P's recursion with Jacobians I + a_j e3^T, in the stepper's closed form
            a = torch.stack([-dy * fo.dt, dx * fo.dt, torch.zeros_like(dx)], -1)[None]
            covs = coast_covariance(P, Q, a)[0]
        P = covs[-1:]
        # the statistic's ring and the speeds: each row writes its slot (an empty entry, its
        # speed) and drops what the slot held; the sums take them in forward's order
        at = k.long() + torch.arange(steps, device=k.device)
        slots, speed_slots = torch.remainder(at, self.slots), torch.remainder(at, self.window)
        sums = torch.cumsum(torch.cat([sums, -ring[0, slots]]), 0)[-1:]
        ring = ring.index_fill(1, slots, 0.0)
        speed = u[:, 0].abs()
        speed_sum = torch.cumsum(torch.cat([speed_sum, torch.stack(
            [speed, -speeds[0, speed_slots]], 1).reshape(-1)]), 0)[-1:]
        speeds = speeds.index_copy(1, speed_slots, speed[None])
        return (wrap_heading(poses[:, :3]), covs[:, :3, :3], poses[-1:], P, bodies[-1:], u[-1:],
                last, dead[-1:], gap + steps, heading, ring, sums, speeds, speed_sum, k + steps,
                started)

    def forward(self, m: torch.Tensor, u: torch.Tensor, *state: torch.Tensor
                ) -> tuple[torch.Tensor, ...]:
        """One step: measurement m (B, 3) (a NaN row: no fix) or a receiver's row (B, 8)
        (:data:`lbo.filters.measure.CHANNELS`), input u (B, 2) (or (B, 3) of :attr:`inputs`:
        without ``r_m`` a gyro filter turns with the bicycle) -> pose (B, 3) (psi wrapped),
        its covariance (B, 3, 3), and the new state (:data:`STATE_NAMES`). Before the first
        row with a position and a heading the pose and its covariance are NaN."""
        (z, P, body, u_prev, last, dr, gap, heading, ring, sums, speeds, speed_sum, k,
         started) = state
        fo = self.window_filter
        if u.shape[1] < len(self.inputs):  # no gyro: the bicycle turns the heading
            u = torch.cat([u, u[:, :1] * 0.0 + math.nan], 1)
        if m.shape[1] == 3:  # the paper's row: no accuracy, no course
            m = torch.cat([m, (m[:, :1] * 0.0 + math.nan).repeat(1, 5)], 1)
        row, there = m, m == m  # (B, 8), and where it is not NaN
        ch, got = row_channels(row), row_channels(there)
        m = ch.pose  # (B, 3)
        position, measured = got.fix[:, 0] & got.fix[:, 1], got.heading
        if not self.fixes:
            position, measured = torch.ones_like(position), torch.ones_like(measured)
        fix = position & measured  # a full fix, what the noise statistic counts
        course = got.course & ~measured
        held = torch.stack([position, position, measured | course], 1)  # x_m, y_m, heading
        m0 = torch.where(fix[:, None], m, torch.zeros_like(m))
        meas = torch.where(held, torch.cat([ch.fix, torch.where(
            measured, ch.heading, ch.course)[:, None]], 1), torch.zeros_like(m))
        first = position & held[:, 2] & (started < 0.5)
        going = started > 0.5
        one = torch.ones_like(m[:, 0])
        zero = torch.zeros_like(one)

        # -- the statistic: one entry in, the one of N steps ago out
        if self.fixes:  # a fix's residual against dead reckoning: two fixes' noise
            dr = bicycle_step(dr, u_prev[:, 0], u_prev[:, 1], fo.dt, fo.wheelbase)
            gap = gap + 1
            d, scale, counted = wrap_heading(m0 - dr), 2, (fix & going).to(m.dtype)
            entry_gap = counted * gap
            dr = torch.where(fix[:, None], m0, dr)
            gap = torch.where(fix, zero, gap)
        else:  # the second difference: i.i.d. noise, variance 6 s^2
            d, scale = wrap_heading(m0 - 2 * last[:, 1] + last[:, 0]), 6
            counted, entry_gap = (k >= 2).to(m.dtype) * one, zero
            last = torch.stack([last[:, 1], m0], 1)
        entry = torch.stack([d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1], d[:, 2] ** 2], 1)
        entry = torch.cat([counted[:, None] * (entry / scale), counted[:, None],
                           entry_gap[:, None]], 1)
        slot = torch.remainder(k, self.slots).long()
        sums = sums + entry - ring.index_select(1, slot)[:, 0]
        ring = ring.index_copy(1, slot, entry[:, None])
        speed_slot = torch.remainder(k, self.window).long()
        speed_sum = speed_sum + u[:, 0].abs() - speeds.index_select(1, speed_slot)[:, 0]
        speeds = speeds.index_copy(1, speed_slot, u[:, 0].abs()[:, None])
        seen = torch.clamp(k + 1, max=float(self.window))
        heading = torch.where(held[:, 2], meas[:, 2], heading)
        R_model = self._noise(sums, speed_sum / seen, heading)
        # in inference a step leaves out what no filter of the batch uses: the same numbers (a
        # torch.where whose condition is all False is its other operand), in less time. Traced,
        # compiled or exported, and with gradients, it stays one graph without branches
        lean = not (torch.is_grad_enabled() or torch.jit.is_tracing()
                    or torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export())
        # full fixes alone, no accuracy reported: R is the noise model's
        plain = lean and bool(measured.all()) and not (got.sigma.any() or got.course.any())
        R = R_model if plain else self._step_cov(R_model, ch, got, measured)

        # -- the filter: predict with u_{k-1}, update with m_k (lbo.models.filter_step)
        Q = self._process_cov(heading)
        drift_var = None
        if self.n == 5:
            drift_var = self._drift_variance(R)
            Q = Q + fo.drift_walk(drift_var)
        prior = fo.predict(z, P, u_prev[:, 0], u_prev[:, 1], body, Q,
                           u_prev[:, 2] if self.gyro else None)
        z_upd, P_upd = fo.correct(prior.z, prior.P, meas, R, held.to(m.dtype))

        # -- where the filter goes on, where it has no fix, where it starts (its first fix)
        if self.keep_prior:  # the smoother's: the prior and cov(x_{k-1|k-1}, x_{k|k-1}), the
            # latter none where the filter starts afresh
            self.last_prior = (prior.z, prior.P, torch.where(
                going[:, None, None], mm(P, prior.F.transpose(1, 2)), torch.zeros_like(P)))
        update = held.any(1) & going
        z = torch.where(update[:, None], z_upd, prior.z)
        P = torch.where(update[:, None, None], P_upd, prior.P)
        body = prior.body
        if not lean or bool(first.any()):  # lean: the start where a filter starts
            # the noise model's R is alpha = 1's at the start (its statistic holds nothing
            # yet); what the receiver reports is as sure as it says
            start_z, start_P = fo.start(meas, self._step_cov(START_SCALE * R_model, ch, got,
                                                             measured), drift_var)
            z = torch.where(first[:, None], start_z, z)
            P = torch.where(first[:, None, None], start_P, P)
            body = torch.where(first[:, None], fo.body_start(u[:, 0], u[:, 1]), body)
            started = torch.where(first, one, started)
        out, cov = wrap_heading(z[:, :3]), P[:, :3, :3]
        if not lean or not bool((started > 0.5).all()):  # lean: NaN before a start
            out = torch.where(started[:, None] > 0.5, out, torch.full_like(out, math.nan))
            cov = torch.where(started[:, None, None] > 0.5, cov, torch.full_like(cov, math.nan))
        else:  # never a view of the state: a caller may write into it
            cov = cov.clone()
        return (out, cov, z, P, body, u, last, dr, gap, heading, ring, sums, speeds,
                speed_sum, k + 1, started)

    def run(self, m: torch.Tensor, u: torch.Tensor, smooth: bool = False,
            lengths: np.ndarray | None = None) -> Filtered:
        """Every step of G logs: m (G, T, 3) (NaN rows: no fix), u (G, T, 2|3) -> their
        :class:`Filtered`, the numbers of T calls of :meth:`forward` from :meth:`initial_state`.
        ``smooth``: the RTS smoother's poses and covariances (:func:`lbo.filters.smoother.rts`),
        over the full state and the first ``lengths`` (G,) steps of each log (None: all)."""
        state = self.initial_state(m.shape[0], m.device)
        poses, covs, bodies, record = [], [], [], []
        self.keep_prior = smooth
        for k in range(m.shape[1]):
            pose, cov, *state = self(m[:, k], u[:, k], *state)
            poses.append(pose)
            covs.append(cov)
            bodies.append(state[2])
            if smooth:
                record.append((state[0], state[1], *self.last_prior))
        body = torch.stack(bodies, 1)
        if not smooth:
            return Filtered(torch.stack(poses, 1), torch.stack(covs, 1), body)
        from lbo.filters.smoother import rts

        x_f, P_f, x_p, P_p, cross = (torch.stack(t, 1).cpu().numpy() for t in zip(*record))
        x_s, P_s = rts(x_f, P_f, x_p, P_p, cross, lengths=lengths)
        pose = torch.from_numpy(x_s[..., :3]).to(m.device)
        pose = torch.where(torch.isfinite(torch.stack(poses, 1)), pose,
                           torch.full_like(pose, math.nan))  # before the first fix
        return Filtered(pose, torch.from_numpy(P_s[..., :3, :3]).to(m.device), body)


class Filtered(NamedTuple):
    """:meth:`RecursiveFilter.run`'s result (tensors; numpy arrays from :func:`run_arrays`):
    pose (G, T, 3), cov (G, T, 3, 3), body (G, T, 2) the carried ``[v_y, r]``."""

    pose: Any
    cov: Any
    body: Any


def run_arrays(net: WindowFilter, m: np.ndarray, u: np.ndarray, smooth: bool = False,
               lengths: np.ndarray | None = None, device: str = "cpu") -> Filtered:
    """:meth:`RecursiveFilter.run` of the window filter ``net`` on numpy arrays: m (G, T, 3)
    (NaN rows: no fix), u (G, T, 2) -> its :class:`Filtered`, as numpy arrays."""
    rec = RecursiveFilter(net).to(device)
    with torch.inference_mode():
        out = rec.run(torch.from_numpy(np.require(m, np.float64, "W")).to(device),
                      torch.from_numpy(np.require(u, np.float64, "W")).to(device),
                      smooth=smooth, lengths=lengths)
    return Filtered(*(t.cpu().numpy() for t in out))
