"""The learned filters' one step, in torch: start at a row, predict with the process model,
correct with the channels a row holds.

Both forms of the window filter take this step and no other. The window form
(:class:`lbo.models.filternet.WindowFilter`) loops it over a window from the window's first
row; its recursive form (:class:`lbo.models.recursive.RecursiveFilter`) takes it once per
sample. What they hand it differs, and that is all that differs:

- R: the window form's is the one its whole window's noise statistic gives (each row's, with a
  receiver's reported accuracies); the recursive form's is its running statistic's, which
  grows step by step. So the recursive form run over a window's rows from a cold start is not
  the window form's estimate (a few millimetres apart, at most centimetres);
- the frame: the window form's is its anchor's, the recursive form's world axes (its Q is
  turned by the latest fix's heading);
- P at the start: R in the window form, :data:`lbo.models.recursive.START_SCALE` R in the
  recursive form, whose statistic has seen nothing yet.

The states: n = 3, the pose ``[x, y, psi]``; 4, and a gyro's bias b, the heading turned by
the gyro's last reading less b (``model.gyro``); 5, and a Gauss-Markov GNSS drift
``[b_x, b_y]`` that the position fixes measure with the pose (``model.drift``).

The correction is :func:`lbo.models.update.masked_update`, Joseph's form, with the channels a
row holds (a receiver's rows hold some; the paper's windows every channel or none).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import nn

from lbo.filters import gyro as gyro_model
from lbo.models.motion import pose_jacobian
from lbo.models.poses import wrap_heading
from lbo.models.update import masked_update, mm

if TYPE_CHECKING:
    _Host = nn.Module
else:  # a mixin, as lbo.models.motion.ProcessModel
    _Host = object


class Prior(NamedTuple):
    """A step's prediction: states z (B, n), covariances P (B, n, n), the Jacobian F
    (B, n, n) that moved them there, and the process model's next body state (B, 2)."""

    z: torch.Tensor
    P: torch.Tensor
    F: torch.Tensor
    body: torch.Tensor


class FilterStep(_Host):
    """The filter step of a :class:`lbo.models.filternet.WindowFilter` (a mixin beside
    :class:`lbo.models.motion.ProcessModel`, whose :meth:`predict_pose` it calls)."""

    if TYPE_CHECKING:  # the host's buffers (or parameters) and settings
        states: int
        eye: torch.Tensor  # (n, n), in the module's dtype
        dt: float
        log_drift_tau: torch.Tensor
        log_gyro_sigma: torch.Tensor
        log_bias_sigma: torch.Tensor
        log_bias_walk: torch.Tensor

        def predict_pose(self, z: torch.Tensor, v: torch.Tensor, delta: torch.Tensor,
                         body: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
            ...

    def gyro_turn(self, reading: torch.Tensor, v: torch.Tensor, bias: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The gyro-driven heading's turn over one step, for the gyro's last readings
        (rad/s, NaN: none yet), speeds (m/s) and bias estimates (rad/s), each (B,): the
        turn ``(r_m - b) dt`` (0 at rest: a car that stands does not turn, whatever the gyro
        reads), its derivative in b, and whether a reading is held (elsewhere the process
        model turns the heading); each (B,). One rule for the step and the recursive form's
        coast."""
        seen = reading == reading  # not NaN
        turning = seen & (v.abs() >= gyro_model.STILL_SPEED)
        zero = torch.zeros_like(bias)
        turn = torch.where(turning, reading - bias, zero) * self.dt
        return turn, torch.where(turning, -self.dt * torch.ones_like(bias), zero), seen

    def drift_phi(self) -> torch.Tensor:
        """The GNSS drift's factor over one step, ``exp(-1 / tau)`` (tau in steps), ()."""
        return torch.exp(-torch.exp(-self.log_drift_tau))

    def drift_walk(self, var_b: torch.Tensor) -> torch.Tensor:
        """The drift's process noise (B, 5, 5) for its stationary variances var_b (B,):
        ``var_b (1 - phi^2)`` on ``b_x`` and ``b_y``, so that the drift keeps that variance."""
        drift = self.eye[3:]  # (2, 5) selector
        return (var_b * (1 - self.drift_phi() ** 2))[:, None, None] * (drift.T @ drift)

    def measurement_matrix(self) -> torch.Tensor:
        """H (3, n): the pose, plus the drift on x and y."""
        eye = self.eye
        if self.states == 5:  # m = pose + [b_x, b_y, 0]
            return eye[:3] + torch.cat([eye[3:], torch.zeros_like(eye[:1])])
        return eye[:3]

    def start(self, meas: torch.Tensor, R: torch.Tensor, drift_var: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """The filters started at a row: its measurement (B, 3) with R (B, 3, 3) as the
        pose's covariance, and the other states' priors: no bias, with its learned prior
        variance; no drift, of stationary variance ``drift_var`` (B,), whose error the pose
        shares (the fix's error is its white noise and the drift). Returns z (B, n) and
        P (B, n, n)."""
        if self.states == 3:
            return meas, R
        zeros = torch.zeros_like(R[:, :, :1])
        if self.states == 4:
            var_b = torch.exp(2 * self.log_bias_sigma) * torch.ones_like(R[:, :1, :1])
            P = torch.cat([torch.cat([R, zeros], 2), torch.cat([zeros.transpose(1, 2), var_b],
                                                                2)], 1)
            return torch.cat([meas, torch.zeros_like(meas[:, :1])], -1), P
        if drift_var is None:
            raise ValueError("start: a filter with the drift needs drift_var")
        e = self.eye
        xy, bb = e[:2].T @ e[:2], e[3:].T @ e[3:]  # ones at (0, 0), (1, 1) / (3, 3), (4, 4)
        cross = e[:2].T @ e[3:]  # ones at (0, 3), (1, 4)
        P = e[:3].T @ R @ e[:3] + drift_var[:, None, None] * (xy - cross - cross.T + bb)
        return torch.cat([meas, torch.zeros_like(meas[:, :2])], -1), P

    def predict(self, z: torch.Tensor, P: torch.Tensor, v: torch.Tensor, delta: torch.Tensor,
                body: torch.Tensor, Q: torch.Tensor, reading: torch.Tensor | None = None
                ) -> Prior:
        """States z (B, n) and covariances P (B, n, n) moved one step by the inputs V (m/s)
        and delta (rad) (B,) and the body state (B, 2), with the process noise Q ((n, n) or
        (B, n, n); its heading's the process model's): the :class:`Prior`. With the bias
        (n = 4), the gyro's last reading (B,) (NaN: none yet) turns the heading where it is
        held, with the gyro's learned noise in place of Q's, and the bias walks."""
        n = self.states
        # the pose alone: z itself where it is all the state (a slice is an op more a step)
        pose, f02, f12, body = self.predict_pose(z if n == 3 else z[:, :3], v, delta, body)
        if n == 3:
            F = pose_jacobian(f02, f12)
        else:
            zero, one = torch.zeros_like(f02), torch.ones_like(f02)
            if n == 4:
                if reading is None:
                    raise ValueError("predict: a filter with the gyro's bias needs a reading")
                turn, f23, seen = self.gyro_turn(reading, v, z[:, 3])
                psi = torch.where(seen, z[:, 2] + turn, pose[:, 2])
                pose = torch.stack([pose[:, 0], pose[:, 1], psi, z[:, 3]], -1)
                rows = [[one, zero, f02, zero], [zero, one, f12, zero],
                        [zero, zero, one, f23], [zero, zero, zero, one]]
                e = self.eye > 0.5
                heading, bias = e[2][:, None] & e[2], e[3][:, None] & e[3]
                Q = torch.where(heading & seen[:, None, None],
                                torch.exp(2 * self.log_gyro_sigma), Q)
                Q = torch.where(bias, torch.exp(2 * self.log_bias_walk), Q)
            else:
                phi = self.drift_phi()
                pose = torch.cat([pose, phi * z[:, 3:]], -1)
                rows = [[one, zero, f02, zero, zero], [zero, one, f12, zero, zero],
                        [zero, zero, one, zero, zero], [zero, zero, zero, phi * one, zero],
                        [zero, zero, zero, zero, phi * one]]
            F = torch.stack([torch.stack(row, -1) for row in rows], -2)
        return Prior(pose, mm(mm(F, P), F.transpose(1, 2)) + Q, F, body)

    def correct(self, z: torch.Tensor, P: torch.Tensor, meas: torch.Tensor, R: torch.Tensor,
                held: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The update of states z (B, n) and covariances P (B, n, n) by measurements
        ``[x, y, heading]`` (B, 3) of covariance R (B, 3, 3): with the channels where
        ``held`` (B, 3) is 1 (None: every channel), in Joseph's form (:func:`masked_update`).
        Returns the updated z and P."""
        if self.states == 3:  # the state is the pose measured: H = I, its products left out
            return masked_update(z, P, wrap_heading(meas - z), R, None, held)
        H = self.measurement_matrix()
        # with the gyro's bias (n = 4) H z is the pose, a slice; the drift's (n = 5) adds to it
        Hz = mm(H, z.unsqueeze(-1)).squeeze(-1) if self.states == 5 else z[:, :3]
        return masked_update(z, P, wrap_heading(meas - Hz), R, H, held)
