"""A learned noise model over a differentiable window EKF: the robust observer.

The network judges the measurement noise from the window and a Kalman filter on the
kinematic bicycle, run over the window, turns that judgement into an estimate. It is never
told alpha. What it learns:

- the measurement-noise sigmas R (one per channel): an MLP reads the log mean squares of
  the window's second differences (a statistic dominated by measurement noise, which the
  smooth motion hardly touches) and the mean speed, and outputs log sigma;
- a scale on the process noise Q (initialised at the noise preset's);
- with ``residual > 0``, the model error of the kinematic bicycle: a small net of V, delta
  and the process model's yaw rate of the step before corrects the yaw rate, adds a side slip
  of the rear axle and a speed scale (a car that slips turns less than its steering says and
  its rear axle moves sideways); zero-initialised, it starts as the kinematic bicycle.
- with ``body="single_track"``, a single-track body in place of the kinematic bicycle: two more
  carried states, the lateral speed v_y and the yaw rate r, move by Newton's laws under the two
  axles' lateral forces, each a saturating curve ``p tanh(k a / p)`` of its slip angle a. What
  it learns: both axles' cornering stiffness k and peak force p (per unit mass), where the
  centre of gravity sits between them, the yaw inertia per unit mass, and the speed below which
  the car rolls as the kinematic bicycle (there the slip angles are singular). It starts at a
  generic car (equal axles, 0.5 g each, the centre of gravity mid-way), not at the truth's.

With a sixth input channel, ``fix`` (``in_features=6``), steps without a position fix get a
prediction-only step, the filter starts at the window's first fix, and the noise statistic is
the mean square of the fixes' residuals against dead reckoning from the previous fix (the
second differences need fixes at three consecutive steps).

Trained end to end through the filter on the MSE of the final estimate, over windows of
alphas drawn from a wide range, it learns to be the EKF that alpha calls for."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from lbo.core.checks import integer, number
from lbo.core.errors import LboError
from lbo.models.poses import wrap_heading

SUBSTEPS = 4
"""Euler sub-steps per sampling period of the single-track body's lateral states."""
BODIES = ("kinematic", "single_track")
"""The process model's bodies (``model.body``)."""
BODY_PARAMETERS = ("log_stiffness", "log_peak", "front_logit", "log_gyration", "log_v_kinematic")
"""The single-track body's learned constants (:meth:`WindowFilter.body_parameters`)."""


def check_sigmas(name: str, values: Sequence[float]) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(math.isfinite(v) and v > 0 for v in out):
        raise LboError(f"model.{name}: expected three sigmas > 0 for [x (m), y (m), psi (rad)], "
                       f"got {values!r}")
    return out  # type: ignore[return-value]


def frame_model(module: nn.Module, window: int, in_features: int, dt: float,
                wheelbase: float) -> None:
    """Set what a model over the kinematic bicycle in the latest fix's frame holds (the window
    filter, KalmanNet), each checked in one line: ``physical`` (it reads and writes metres and
    radians, see WindowNet), ``feature_modes``, ``window`` (>= 4), ``in_features`` (5, or 6
    with the fix channel) and ``fixes``, ``dt`` (s) and ``wheelbase`` (m)."""
    module.physical = True
    module.feature_modes = ("frame",)
    module.window = integer(window, "window", 4)
    module.in_features = integer(in_features, "in_features", 5)
    if module.in_features > 6:
        raise LboError(f"model.in_features: expected 5, or 6 with the fix channel, "
                       f"got {in_features!r}")
    module.fixes = module.in_features == 6
    module.dt = number(dt, "model.dt", low=0.0, low_open=True, form="a period in seconds > 0")
    module.wheelbase = number(wheelbase, "model.wheelbase", low=0.0, low_open=True,
                              form="a length in metres > 0")


def _tan(a: torch.Tensor) -> torch.Tensor:
    """tan as sin / cos: ONNX Runtime has no float64 Tan, and the recursive form runs in
    float64 (equal to torch.tan to rounding)."""
    return torch.sin(a) / torch.cos(a)


def bicycle_step(z: torch.Tensor, v: torch.Tensor, delta: torch.Tensor, dt: float,
                 wheelbase: float) -> torch.Tensor:
    """One step of the kinematic bicycle (:func:`lbo.sim.vehicle.step` in torch): poses
    (B, 3) moved by speeds and steering angles (B,) over ``dt``."""
    psi = z[:, 2]
    return z + torch.stack([v * torch.cos(psi), v * torch.sin(psi),
                            v * _tan(delta) / wheelbase], -1) * dt


def _inverse_sym3(s: torch.Tensor) -> torch.Tensor:
    """Inverse of symmetric positive-definite (B, 3, 3) matrices by cofactors.

    Written out so that TorchScript and ONNX export it (ONNX has no matrix inverse).
    """
    a, b, c = s[:, 0, 0], s[:, 0, 1], s[:, 0, 2]
    d, e, f = s[:, 1, 1], s[:, 1, 2], s[:, 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    rows = [torch.stack([c00, c01, c02], -1), torch.stack([c01, c11, c12], -1),
            torch.stack([c02, c12, c22], -1)]
    return torch.stack(rows, -2) / det[:, None, None]


class WindowFilter(nn.Module):
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
    in_features : channels per step: 5, or 6 with the ``fix`` channel (missing fixes).
    residual : width of the process model's learned correction (two hidden layers); 0 keeps
        the kinematic bicycle.
    drift : also estimate a Gauss-Markov GNSS drift on x and y (two more filter states);
        its correlation time and its size relative to the white noise are learned.
    body : the process model's body, ``"kinematic"`` (the bicycle, with the ``residual``
        correction if any) or ``"single_track"`` (lateral speed and yaw rate under learned
        tyre forces).
    body_lr : the single-track body's learning rate as a multiple of the optimiser's
        (:meth:`param_groups`): its seven constants each get a consistent gradient from every
        corner, and travel from the generic car to the one in the data in fewer steps.
    """

    def __init__(self, window: int, dt: float = 0.02, wheelbase: float = 2.7,
                 process_sigma: Sequence[float] = (0.0667, 0.0667, 0.00113),
                 measurement_sigma: Sequence[float] = (1.0, 1.0, 0.0174),
                 hidden: int = 32, in_features: int = 5, residual: int = 0,
                 drift: bool = False, body: str = "kinematic", body_lr: float = 1.0) -> None:
        super().__init__()
        frame_model(self, window, in_features, dt, wheelbase)
        hidden = integer(hidden, "hidden", 1)
        q = torch.tensor(check_sigmas("process_sigma", process_sigma))
        r = torch.tensor(check_sigmas("measurement_sigma", measurement_sigma))
        self.register_buffer("log_q0", q.log())
        self.register_buffer("log_r0", r.log())
        self.log_q_scale = nn.Parameter(torch.zeros(3))
        # features: log mean square second difference per channel (in units of r0), log(1+V)
        # (with fixes, also the log of the mean gap between fixes)
        self.noise = nn.Sequential(nn.Linear(4 + self.fixes, hidden), nn.GELU(),
                                   nn.Linear(hidden, hidden),
                                   nn.GELU(), nn.Linear(hidden, 3))
        nn.init.zeros_(self.noise[-1].weight)
        nn.init.zeros_(self.noise[-1].bias)
        self.residual = integer(residual, "model.residual", 0,
                                form="an integer >= 0 (0: the kinematic bicycle)")
        if not isinstance(drift, bool):
            raise LboError(f"model.drift: expected true or false, got {drift!r}")
        self.drift = drift
        # start at a 10 s correlation time and a drift of 0.3 of the white sigma; without
        # drift, the same values ride along unsaved, so TorchScript compiles either filter
        for name, value in (("log_drift_tau", math.log(10.0 / dt)),
                            ("log_drift_ratio", math.log(0.3))):
            if drift:
                self.register_parameter(name, nn.Parameter(torch.tensor(value)))
            else:
                self.register_buffer(name, torch.tensor(value), persistent=False)
        if body not in BODIES:
            raise LboError(f"model.body: expected one of {', '.join(BODIES)}, got {body!r}")
        if body == "single_track" and residual:
            raise LboError(f"model.residual: expected 0 with model.body=single_track (the "
                           f"single-track body is the learned process model), got {residual!r}")
        self.single_track = body == "single_track"
        self.body_lr = number(body_lr, "model.body_lr", low=0.0, low_open=True,
                              form="a multiple of the learning rate > 0")
        self.substeps = SUBSTEPS  # an attribute: TorchScript reads no module-level int
        # (front, rear) cornering stiffness and peak force per unit mass (m/s^2 per rad, m/s^2),
        # the front axle's share of the wheelbase behind the centre of gravity (l_f / L, as a
        # logit), the yaw inertia per unit mass in units of l_f l_r, and the speed (m/s) below
        # which the body is the kinematic bicycle; unsaved buffers for the kinematic body
        for name, value in (("log_stiffness", torch.full((2,), math.log(50.0))),
                            ("log_peak", torch.full((2,), math.log(0.5 * 9.81))),
                            ("front_logit", torch.tensor(0.0)),
                            ("log_gyration", torch.tensor(0.0)),
                            ("log_v_kinematic", torch.tensor(math.log(3.0)))):
            if self.single_track:
                self.register_parameter(name, nn.Parameter(value))
            else:
                self.register_buffer(name, value, persistent=False)
        self.process: nn.Module = nn.Identity()  # scripted whether or not it is used
        if residual:
            # in: V, delta, the kinematic and the previous yaw rate, each scaled to about 1;
            # out: yaw-rate correction (rad/s), rear side slip (rad), speed scale (_motion)
            self.process = nn.Sequential(nn.Linear(4, residual), nn.GELU(),
                                         nn.Linear(residual, residual), nn.GELU(),
                                         nn.Linear(residual, 3))
            nn.init.zeros_(self.process[-1].weight)
            nn.init.zeros_(self.process[-1].bias)

    def _axles(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The learned distances (l_f, l_r) from the centre of gravity to the front and rear
        axles (m); they sum to the wheelbase."""
        l_f = self.wheelbase * torch.sigmoid(self.front_logit)
        return l_f, self.wheelbase - l_f

    def _body_constants(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                       torch.Tensor, torch.Tensor]:
        """The single-track body's learned constants in physical units: cornering stiffness
        and peak force per unit mass, each (2,) for (front, rear), l_f, l_r, the yaw inertia
        per unit mass and the speed below which it is the kinematic bicycle."""
        l_f, l_r = self._axles()
        return (torch.exp(self.log_stiffness), torch.exp(self.log_peak), l_f, l_r,
                torch.exp(self.log_gyration) * l_f * l_r, torch.exp(self.log_v_kinematic))

    def body_start(self, v: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        """(B, 2) carried body state ``[v_y, r]`` at the first step, inputs (B,): the kinematic
        bicycle's (no slip at the rear axle: v_y = l_r r)."""
        r = v * _tan(delta) / self.wheelbase
        v_y = self._axles()[1] * r if self.single_track else torch.zeros_like(r)
        return torch.stack([v_y, r], -1)

    def param_groups(self) -> list[dict]:
        """The optimiser's parameter groups: the single-track body's constants with
        ``lr_scale`` = ``body_lr``, and every other parameter with 1 (the optimiser's rate)."""
        body = [p for name, p in self.named_parameters() if name in BODY_PARAMETERS]
        rest = [p for name, p in self.named_parameters() if name not in BODY_PARAMETERS]
        return [g for g in ({"params": rest, "lr_scale": 1.0},
                            {"params": body, "lr_scale": self.body_lr}) if g["params"]]

    def body_parameters(self) -> dict[str, float]:
        """The single-track body's learned parameters in physical units: cornering stiffness
        per unit mass ``k_f, k_r`` (m/s^2 per rad, i.e. C / m), peak lateral force per unit
        mass ``peak_f, peak_r`` (m/s^2, i.e. mu F_z / m), ``l_f, l_r`` (m), the yaw inertia per
        unit mass ``inertia`` (m^2, I_z / m) and ``v_kinematic`` (m/s)."""
        k, p, l_f, l_r, inertia, v0 = self._body_constants()
        values = {"k_f": k[0], "k_r": k[1], "peak_f": p[0], "peak_r": p[1], "l_f": l_f,
                  "l_r": l_r, "inertia": inertia, "v_kinematic": v0}
        return {name: float(v.detach()) for name, v in values.items()}

    @staticmethod
    def _lateral_rates(body: torch.Tensor, vx: torch.Tensor, delta: torch.Tensor,
                       k: torch.Tensor, p: torch.Tensor, l_f: torch.Tensor, l_r: torch.Tensor,
                       inertia: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(dv_y/dt, dr/dt), each (B,), of the single-track body (B, 2) at speed vx (B,) with
        the constants of :meth:`_body_constants`."""
        v_y, r = body[:, 0], body[:, 1]
        a_f = delta - (v_y + l_f * r) / vx
        a_r = -(v_y - l_r * r) / vx
        f_f = p[0] * torch.tanh(k[0] * a_f / p[0]) * torch.cos(delta)
        f_r = p[1] * torch.tanh(k[1] * a_r / p[1])
        return f_f + f_r - vx * r, (l_f * f_f - l_r * f_r) / inertia

    def _motion(self, v: torch.Tensor, delta: torch.Tensor, body: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The process model over one step, for inputs (B,) and the carried body state
        ``[v_y, r]`` (B, 2): the rear axle's velocity along and across the heading, the heading
        rate, each (B,), and the next body state (B, 2).

        The kinematic bicycle: ``(v, 0, v tan(delta) / L)``, corrected by the learned residual
        (which reads the yaw rate of the step before, carried as ``r``). The single-track body:
        :data:`SUBSTEPS` Euler sub-steps of its lateral states, whose trapezoid-rule mean over
        the step moves the pose, blended (smoothstep) into the kinematic bicycle below the
        learned speed."""
        r_kin = v * _tan(delta) / self.wheelbase
        if self.single_track:
            k, p, l_f, l_r, inertia, v0 = self._body_constants()
            vx = torch.maximum(v, v0)
            n = self.substeps
            h = self.dt / n
            mean = 0.5 * body / n  # the trapezoid rule's mean of [v_y, r] over the step
            for i in range(n):
                dv_y, dr = self._lateral_rates(body, vx, delta, k, p, l_f, l_r, inertia)
                body = body + h * torch.stack([dv_y, dr], -1)
                mean = mean + (0.5 if i == n - 1 else 1.0) * body / n
            s = torch.clamp(v / v0 - 1, 0.0, 1.0)
            w = s * s * (3 - 2 * s)
            lateral = w * (mean[:, 0] - l_r * mean[:, 1])
            rate = w * mean[:, 1] + (1 - w) * r_kin
            return v, lateral, rate, body
        if self.residual == 0:
            return v, torch.zeros_like(v), r_kin, torch.stack([body[:, 0], r_kin], -1)
        x = torch.stack([0.1 * v, 10.0 * delta, 2.0 * r_kin, 2.0 * body[:, 1]], -1)
        d = self.process(x)
        speed, beta, rate = v * (1 + 0.05 * d[:, 2]), 0.05 * d[:, 1], r_kin + 0.2 * d[:, 0]
        return (speed * torch.cos(beta), speed * torch.sin(beta), rate,
                torch.stack([body[:, 0], rate], -1))

    def _predict_pose(self, z: torch.Tensor, step: torch.Tensor, body: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The process model's prediction of poses z (B, 3) over one step of features
        ``step`` (B, C) (inputs in channels 3 and 4), body (B, 2) the carried body state
        (:meth:`_motion`): the new pose, the Jacobian's two off-diagonal entries d x / d psi
        and d y / d psi, each (B,), and the next body state."""
        along, across, rate, body = self._motion(step[:, 3], step[:, 4], body)
        # the kinematic bicycle moves along its heading at the step's start, as the classical
        # filters' model does; the single-track body along its mid-step heading (second order)
        heading = z[:, 2] + 0.5 * self.dt * rate if self.single_track else z[:, 2]
        c, s = torch.cos(heading), torch.sin(heading)
        dx, dy = along * c - across * s, along * s + across * c
        z = z + torch.stack([dx, dy, rate], -1) * self.dt
        # F = I + dt * [[0, 0, -dy], [0, 0, dx], [0, 0, 0]]
        return z, -dy * self.dt, dx * self.dt, body

    def _drift_filter(self, x: torch.Tensor, R: torch.Tensor, Q: torch.Tensor) -> torch.Tensor:
        """The window filter with two more states: a Gauss-Markov GNSS drift b on x and y,
        ``b' = phi b``, measured as ``m = pose + [b, 0]``. Its correlation time and its size
        relative to the white position noise are learned. (B, N, C) features, (B, 3, 3) R and
        (3, 3) Q -> (B, 3) pose.

        The drift's mean is unobservable from positions alone; what the states buy is a filter
        that knows its position fixes' errors are correlated, and averages them no further
        than that allows."""
        phi = torch.exp(-torch.exp(-self.log_drift_tau))  # exp(-1 / tau), tau in steps
        white = (R[:, 0, 0] * R[:, 1, 1]) ** 0.25  # (B,) white position sigma
        var_b = (torch.exp(self.log_drift_ratio) * white) ** 2  # (B,) stationary variance
        e = torch.eye(5, dtype=x.dtype, device=x.device)
        pose, drift = e[:3], e[3:]  # selectors: (3, 5) and (2, 5)
        H = pose + torch.cat([drift, torch.zeros_like(drift[:1])])  # m = pose + [b_x, b_y, 0]
        Qp = pose.T @ Q @ pose + (var_b * (1 - phi**2))[:, None, None] * (drift.T @ drift)
        start = self._drift_start(R, var_b, e)
        z = torch.cat([x[:, 0, :3], torch.zeros_like(x[:, 0, :2])], -1)
        P = start
        body = self.body_start(x[:, 0, 3], x[:, 0, 4])
        started = x[:, 0, -1] > 0.5  # read only with the fix channel
        zero = torch.zeros_like(x[:, 0, 0])
        one = torch.ones_like(zero)
        for k in range(1, x.shape[1]):
            p, f02, f12, body = self._predict_pose(z[:, :3], x[:, k - 1], body)
            z = torch.cat([p, phi * z[:, 3:]], -1)
            F = torch.stack([torch.stack([one, zero, f02, zero, zero], -1),
                             torch.stack([zero, one, f12, zero, zero], -1),
                             torch.stack([zero, zero, one, zero, zero], -1),
                             torch.stack([zero, zero, zero, phi * one, zero], -1),
                             torch.stack([zero, zero, zero, zero, phi * one], -1)], -2)
            P = F @ P @ F.transpose(1, 2) + Qp
            y = x[:, k, :3] - (H @ z.unsqueeze(-1)).squeeze(-1)
            y = wrap_heading(y)
            PH = P @ H.T  # (B, 5, 3)
            K = PH @ _inverse_sym3(H @ PH + R)
            z_new = z + (K @ y.unsqueeze(-1)).squeeze(-1)
            P_new = (e - K @ H) @ P
            P_new = 0.5 * (P_new + P_new.transpose(1, 2))
            if self.fixes:  # no fix: the prediction; the first fix: start there
                f = x[:, k, 5] > 0.5
                first = (f & ~started)[:, None]
                restart = torch.cat([x[:, k, :3], torch.zeros_like(z[:, 3:])], -1)
                z = torch.where(first, restart, torch.where(f[:, None], z_new, z))
                P = torch.where(first[..., None], start, torch.where(f[:, None, None], P_new, P))
                started = started | f
            else:
                z, P = z_new, P_new
        return wrap_heading(z[:, :3])

    @staticmethod
    def _drift_start(R: torch.Tensor, var_b: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
        """(B, 5, 5) covariance of starting at a fix with zero drift: the pose's error is minus
        the fix's white noise and drift, the drift's is the drift."""
        xy, bb = e[:2].T @ e[:2], e[3:].T @ e[3:]  # ones at (0, 0), (1, 1) / (3, 3), (4, 4)
        cross = e[:2].T @ e[3:]  # ones at (0, 3), (1, 4)
        return e[:3].T @ R @ e[:3] + var_b[:, None, None] * (xy - cross - cross.T + bb)

    def _fix_residuals(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean square residual of each fix against dead reckoning from the previous fix,
        halved (two fixes' noise), (B, 3), and the log of the mean gap between fixes (B, 1).
        A window with fewer than two fixes gets the alpha=1 variance."""
        fix = x[:, :, 5] > 0.5
        dr = x[:, 0, :3]
        seen = fix[:, 0]
        gap = torch.zeros_like(x[:, 0, 0])
        total = torch.zeros_like(x[:, 0, :3])
        count = torch.zeros_like(x[:, 0, 0])
        gaps = torch.zeros_like(count)
        for k in range(1, x.shape[1]):
            dr = bicycle_step(dr, x[:, k - 1, 3], x[:, k - 1, 4], self.dt, self.wheelbase)
            gap = gap + 1
            f = fix[:, k]
            r = x[:, k, :3] - dr
            r = wrap_heading(r)
            use = (f & seen).to(x.dtype)
            total = total + use[:, None] * r ** 2
            count, gaps = count + use, gaps + use * gap
            dr = torch.where(f[:, None], x[:, k, :3], dr)
            gap = torch.where(f, torch.zeros_like(gap), gap)
            seen = seen | f
        some = count > 0
        ms = torch.where(some[:, None], total / (2 * count.clamp_min(1))[:, None],
                         torch.exp(2 * self.log_r0).expand_as(total))
        mean_gap = torch.where(some, gaps / count.clamp_min(1), torch.ones_like(gaps))
        return ms, torch.log(mean_gap)[:, None]

    def measurement_sigma(self, x: torch.Tensor) -> torch.Tensor:
        """The noise model: (B, N, 5|6) features -> (B, 3) measurement sigmas."""
        speed = torch.log1p(x[:, :, 3].abs().mean(1, keepdim=True))
        if self.fixes:
            ms, log_gap = self._fix_residuals(x)
        else:
            m = x[:, :, :3]
            d2 = m[:, 2:] - 2 * m[:, 1:-1] + m[:, :-2]
            d2 = wrap_heading(d2)
            # second differences of i.i.d. noise of variance s^2 have variance 6 s^2
            ms = (d2 ** 2).mean(1) / 6.0
            log_gap = speed[:, :0]  # no column
        log_ratio = 0.5 * torch.log(ms + 1e-12) - self.log_r0  # about log alpha
        # start from the plain moment estimate, exp(log_ratio) * r0 = sqrt(ms)
        log_sigma = log_ratio + self.log_r0 + self.noise(torch.cat([log_ratio, speed, log_gap],
                                                                   1))
        return torch.exp(log_sigma).clamp_min(1e-6)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N, 5|6) features -> (B, 3) state in the anchor's (current measurement's) frame."""
        n = x.shape[1]
        r = self.measurement_sigma(x) ** 2  # (B, 3)
        q = torch.exp(2 * (self.log_q0 + self.log_q_scale))  # (3,)
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        R = r.unsqueeze(-1) * eye  # diagonal matrices, written so that ONNX exports them
        Q = q * eye
        if self.drift:
            return self._drift_filter(x, R, Q)
        z = x[:, 0, :3]
        P = R
        started = x[:, 0, -1] > 0.5  # read only with the fix channel
        body = self.body_start(x[:, 0, 3], x[:, 0, 4])
        for k in range(1, n):
            z, f02, f12, body = self._predict_pose(z, x[:, k - 1], body)
            zero = torch.zeros_like(f02)
            one = torch.ones_like(f02)
            F = torch.stack([torch.stack([one, zero, f02], -1),
                             torch.stack([zero, one, f12], -1),
                             torch.stack([zero, zero, one], -1)], -2)
            P = F @ P @ F.transpose(1, 2) + Q
            y = x[:, k, :3] - z
            y = wrap_heading(y)
            K = P @ _inverse_sym3(P + R)
            z_new = z + (K @ y.unsqueeze(-1)).squeeze(-1)
            P_new = (eye - K) @ P
            P_new = 0.5 * (P_new + P_new.transpose(1, 2))
            if self.fixes:  # no fix: the prediction; the first fix: start there, P = R
                f = x[:, k, 5] > 0.5
                first = (f & ~started)[:, None]
                z = torch.where(first, x[:, k, :3], torch.where(f[:, None], z_new, z))
                P = torch.where(first[..., None], R,
                                torch.where(f[:, None, None], P_new, P))
                started = started | f
            else:
                z, P = z_new, P_new
        return wrap_heading(z)
