"""The window filter's process model: the kinematic bicycle, with an optional learned
correction, or a single-track body with learned tyres.

:class:`ProcessModel` is a mixin of :class:`lbo.models.filternet.WindowFilter`: it registers
the process model's parameters on the filter itself (so a checkpoint's keys are the filter's),
and gives the motion over one step and its Jacobian, which the window form and the recursive
form (:mod:`lbo.models.recursive`) both step with.

- ``residual > 0``: the model error of the kinematic bicycle. A small net of V, delta and the
  process model's yaw rate of the step before corrects the yaw rate, adds a side slip of the
  rear axle and a speed scale (a car that slips turns less than its steering says and its rear
  axle moves sideways); zero-initialised, it starts as the kinematic bicycle.
- ``body="single_track"``: two more carried states, the lateral speed v_y and the yaw rate r,
  move by Newton's laws under the two axles' lateral forces, each a saturating curve
  ``p tanh(k a / p)`` of its slip angle a. What it learns: both axles' cornering stiffness k
  and peak force p (per unit mass), where the centre of gravity sits between them, the yaw
  inertia per unit mass, and the speed below which the car rolls as the kinematic bicycle
  (there the slip angles are singular). It starts at a generic car (equal axles, 0.5 g each,
  the centre of gravity mid-way), not at the truth's. Where the car's geometry is known
  (``body_rear``, weighed at the axles or read from a data sheet), the centre of gravity is
  held there: position fixes see the rear axle, and nothing in them pins how far ahead of it
  the centre of gravity sits, where beta is read.
- ``input_terms``: what undoes the input sensors' errors, learned as three numbers (a factor
  on the speed, an offset and a factor on the steering; :class:`lbo.filters.inputs.InputTerms`)
  and applied to V and delta before either body reads them: the dead reckoning through an
  outage is mostly these. They start at nothing undone.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, cast

import numpy as np
import torch
from torch import nn

from lbo.core.checks import integer, number, require
from lbo.core.errors import LboError
from lbo.filters.inputs import InputTerms

SUBSTEPS = 4
"""Euler sub-steps per sampling period of the single-track body's lateral states."""
BODIES = ("kinematic", "single_track")
"""The process model's bodies (``model.body``)."""
BODY_PARAMETERS = ("log_stiffness", "log_peak", "front_logit", "log_gyration", "log_v_kinematic")
"""The single-track body's learned constants (:meth:`ProcessModel.body_parameters`)."""
TERMS_SCALE = 0.1
"""The input terms' parameters move their terms (the speed's and steering's log factors, the
offset in rad) this much per unit: an optimiser's step of 1e-3 moves an offset by 0.1 mrad,
and its rate's whole schedule reaches the few percent and tens of mrad sensors are off."""


def tan(a: torch.Tensor) -> torch.Tensor:
    """tan as sin / cos: ONNX Runtime has no float64 Tan, and the recursive form runs in
    float64 (equal to torch.tan to rounding)."""
    return torch.sin(a) / torch.cos(a)


def bicycle_step(z: torch.Tensor, v: torch.Tensor, delta: torch.Tensor, dt: float,
                 wheelbase: float) -> torch.Tensor:
    """One step of the kinematic bicycle (:func:`lbo.sim.vehicle.step` in torch): poses
    (B, 3) moved by speeds and steering angles (B,) over ``dt``."""
    psi = z[:, 2]
    return z + torch.stack([v * torch.cos(psi), v * torch.sin(psi),
                            v * tan(delta) / wheelbase], -1) * dt


def pose_jacobian(f02: torch.Tensor, f12: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) Jacobian of a pose step from its two off-diagonal entries d x / d psi and
    d y / d psi (B,) (:meth:`ProcessModel.predict_pose`), built by stacking so that ONNX
    exports it."""
    zero, one = torch.zeros_like(f02), torch.ones_like(f02)
    return torch.stack([torch.stack([one, zero, f02], -1), torch.stack([zero, one, f12], -1),
                        torch.stack([zero, zero, one], -1)], -2)


# the type checker sees the mixin as the nn.Module it is mixed into; at run time it is a
# plain class, as before
if TYPE_CHECKING:
    _Host = nn.Module
else:
    _Host = object


class ProcessModel(_Host):
    """The process model of a module with ``dt`` (s) and ``wheelbase`` (m) (a mixin of an
    ``nn.Module``): :meth:`build_process` registers its parameters, :meth:`predict_pose` moves
    poses over one step. (No class-level annotations at run time: TorchScript would read them
    as the module's attributes.)"""

    if TYPE_CHECKING:  # set by lbo.models.frame.frame_model on each host
        physical: bool
        feature_modes: tuple[str, ...]
        window: int
        in_features: int
        receiver: bool
        fixes: bool
        dt: float
        wheelbase: float
        # build_process's buffers (the kinematic body) or parameters (the single-track)
        log_stiffness: torch.Tensor
        log_peak: torch.Tensor
        front_logit: torch.Tensor
        log_gyration: torch.Tensor
        log_v_kinematic: torch.Tensor
        input_term_values: torch.Tensor

    def build_process(self, residual: int, body: str, body_lr: float,
                      input_terms: bool = False, body_rear: float | None = None) -> None:
        """Register the process model: ``residual`` the width of the kinematic bicycle's
        learned correction (0: none), ``body`` one of :data:`BODIES`, ``body_lr`` the
        single-track body's learning rate as a multiple of the optimiser's, ``input_terms``
        whether the inputs' terms are learned, ``body_rear`` the single-track body's centre
        of gravity ahead of the rear axle (m), held (None: learned); each checked in one
        line."""
        assert isinstance(self, nn.Module)
        self.residual = integer(residual, "model.residual", 0,
                                form="an integer >= 0 (0: the kinematic bicycle)")
        if body not in BODIES:
            raise LboError(f"model.body: expected one of {', '.join(BODIES)}, got {body!r}")
        if body == "single_track" and residual:
            raise LboError(f"model.residual: expected 0 with model.body=single_track (the "
                           f"single-track body is the learned process model), got {residual!r}")
        self.single_track = body == "single_track"
        self.body_lr = number(body_lr, "model.body_lr", low=0.0, low_open=True,
                              form="a multiple of the learning rate > 0")
        self.substeps = SUBSTEPS  # an attribute: TorchScript reads no module-level int
        front = 0.0
        if body_rear is not None:
            form = (f"null (learned) or the centre of gravity's distance ahead of the rear "
                    f"axle in m, in (0, {self.wheelbase:g}) (the wheelbase), with "
                    f"model.body=single_track")
            body_rear = number(body_rear, "model.body_rear", low=0.0, low_open=True, form=form)
            require(body_rear < self.wheelbase and self.single_track, "model.body_rear", form,
                    body_rear)
            front = math.log((self.wheelbase - body_rear) / body_rear)  # logit(l_f / L)
        # (front, rear) cornering stiffness and peak force per unit mass (m/s^2 per rad, m/s^2),
        # the front axle's share of the wheelbase behind the centre of gravity (l_f / L, as a
        # logit), the yaw inertia per unit mass in units of l_f l_r, and the speed (m/s) below
        # which the body is the kinematic bicycle; unsaved buffers for the kinematic body
        for name, value in (("log_stiffness", torch.full((2,), math.log(50.0))),
                            ("log_peak", torch.full((2,), math.log(0.5 * 9.81))),
                            ("front_logit", torch.tensor(front)),
                            ("log_gyration", torch.tensor(0.0)),
                            ("log_v_kinematic", torch.tensor(math.log(3.0)))):
            if self.single_track and not (name == "front_logit" and body_rear is not None):
                self.register_parameter(name, nn.Parameter(value))
            else:  # held: saved with the body, so its checkpoint has the key either way
                self.register_buffer(name, value, persistent=self.single_track)
        self.process: nn.Module = nn.Identity()  # scripted whether or not it is used
        if residual:
            # in: V, delta, the kinematic and the previous yaw rate, each scaled to about 1;
            # out: yaw-rate correction (rad/s), rear side slip (rad), speed scale (motion)
            self.process = nn.Sequential(nn.Linear(4, residual), nn.GELU(),
                                         nn.Linear(residual, residual), nn.GELU(),
                                         nn.Linear(residual, 3))
            head = cast(nn.Linear, self.process[-1])  # the Linear made just above
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)
        if not isinstance(input_terms, bool):
            raise LboError(f"model.input_terms: expected true or false, got {input_terms!r}")
        self.input_terms = input_terms
        self.terms_scale = TERMS_SCALE  # an attribute: TorchScript reads no module-level float
        # (log speed factor, steering offset, log steering factor) / TERMS_SCALE; without,
        # the same zeros ride along unsaved, so TorchScript compiles either model
        if input_terms:
            self.input_term_values = nn.Parameter(torch.zeros(3))
        else:
            self.register_buffer("input_term_values", torch.zeros(3), persistent=False)

    def learned_inputs(self) -> InputTerms:
        """The input terms learned (``input_terms``; otherwise none undo anything)."""
        a, b, c = (float(v) * self.terms_scale for v in self.input_term_values.detach().cpu())
        return InputTerms(math.exp(a), b, math.exp(c))

    def _undo_inputs(self, v: torch.Tensor, delta: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """The inputs V and delta (B,) with the learned terms' errors undone
        (:meth:`lbo.filters.inputs.InputTerms.undo` in torch)."""
        t = self.input_term_values * self.terms_scale
        return v * torch.exp(t[0]), (delta - t[1]) * torch.exp(t[2])

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
        r = v * tan(delta) / self.wheelbase
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

    def implied_inputs(self, u: np.ndarray, moving: float = 3.0) -> InputTerms:
        """The input terms (:class:`lbo.filters.inputs.InputTerms`) that the process model
        undoes on inputs ``u`` (T, 2) ``[V, delta]``. Without a learned correction of the
        kinematic bicycle: the learned terms (:meth:`learned_inputs`), or none. With one
        (``residual > 0``, after the learned terms where there are), as medians over the rows
        faster than ``moving`` (m/s): the speed factor is its speed over V; the steering offset
        is the one whose yaw rate at that speed, ``f V tan(delta - offset) / L``, is its
        corrected one, to first order, with the yaw rate of the step before taken as the
        kinematic one. The steering factor is not told apart from the correction's other parts
        there and stays 1."""
        rows = np.asarray(u, dtype=float)
        rows = rows[rows[:, 0] > moving]
        if self.residual == 0 or self.single_track or not len(rows):
            return self.learned_inputs()
        ref = next(iter(self.parameters()))  # the correction's dtype and device
        v, delta = (torch.as_tensor(c, dtype=ref.dtype, device=ref.device) for c in rows.T)
        r = v * tan(delta) / self.wheelbase
        with torch.no_grad():
            along, across, rate, _ = self.motion(v, delta, torch.stack([torch.zeros_like(r), r],
                                                                       -1))
        speed = torch.hypot(along, across) / v
        # the yaw rate of the corrected speed: f V tan(delta - offset) / L
        offset = (speed * r - rate) * self.wheelbase * torch.cos(delta) ** 2 / (speed * v)
        return InputTerms(float(speed.median()), float(offset.median()))

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

    def motion(self, v: torch.Tensor, delta: torch.Tensor, body: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The process model over one step, for inputs (B,) and the carried body state
        ``[v_y, r]`` (B, 2): the rear axle's velocity along and across the heading, the heading
        rate, each (B,), and the next body state (B, 2).

        The kinematic bicycle: ``(v, 0, v tan(delta) / L)``, corrected by the learned residual
        (which reads the yaw rate of the step before, carried as ``r``). The single-track body:
        :data:`SUBSTEPS` Euler sub-steps of its lateral states, whose trapezoid-rule mean over
        the step moves the pose, blended (smoothstep) into the kinematic bicycle below the
        learned speed. With ``input_terms``, both read V and delta with the learned terms'
        errors undone."""
        if self.input_terms:
            v, delta = self._undo_inputs(v, delta)
        r_kin = v * tan(delta) / self.wheelbase
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

    def predict_pose(self, z: torch.Tensor, v: torch.Tensor, delta: torch.Tensor,
                     body: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The process model's prediction of poses z (B, 3) over one step of inputs V (m/s)
        and delta (rad), each (B,), body (B, 2) the carried body state (:meth:`motion`): the
        new pose, the Jacobian's two off-diagonal entries d x / d psi and d y / d psi, each
        (B,), and the next body state."""
        along, across, rate, body = self.motion(v, delta, body)
        # the kinematic bicycle moves along its heading at the step's start, as the classical
        # filters' model does; the single-track body along its mid-step heading (second order)
        heading = z[:, 2] + 0.5 * self.dt * rate if self.single_track else z[:, 2]
        c, s = torch.cos(heading), torch.sin(heading)
        dx, dy = along * c - across * s, along * s + across * c
        z = z + torch.stack([dx, dy, rate], -1) * self.dt
        # F = I + dt * [[0, 0, -dy], [0, 0, dx], [0, 0, 0]]
        return z, -dy * self.dt, dx * self.dt, body

