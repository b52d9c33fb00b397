"""Dynamic single-track vehicle with saturating lateral tyre forces: a car that slips.

The kinematic bicycle (:mod:`lbo.sim.vehicle`) assumes that the wheels roll without slip. A car in a
corner needs slip angles to make lateral force: it understeers (turns less than the steering
says), and its rear axle moves sideways, at the rear slip angle off its heading. This model has
both (Rajamani, *Vehicle Dynamics and Control*, ch. 2-3), at a given longitudinal speed
``v_x = V``:

    m (v_y' + v_x r) = F_yf cos(delta) + F_yr,      I_z r' = l_f F_yf cos(delta) - l_r F_yr,
    a_f = delta - (v_y + l_f r) / v_x,              a_r = -(v_y - l_r r) / v_x,
    F = mu F_z tanh(C a / (mu F_z)),                F_zf = m g l_r / L,  F_zr = m g l_f / L,

with ``v_y`` the lateral speed of the centre of gravity and ``r`` the yaw rate. Each tyre's
force is linear (``C a``) at small slip and saturates at ``mu F_z``.

State ``s = [x, y, psi, v_y, r]`` (m, m, rad, m/s, rad/s): the rear axle's pose, as in every
log, and the two lateral states. The rear axle moves at ``(v_x, v_y - l_r r)`` in the body
frame. Input ``u = [V, delta]`` as for the kinematic bicycle.

Below ``v_kinematic`` the dynamic equations are singular (the slip angles divide by v_x): the car
moves as the kinematic bicycle there, blending smoothly to the dynamic model at twice that
speed. The lateral states are integrated at ``max(v_x, v_kinematic)``, so they stay finite and
are right again once the car is fast. Everything is vectorised over leading batch dimensions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from lbo.core.checks import integer, number

if TYPE_CHECKING:
    from lbo.sim.truth import Car

G = 9.81  # m/s^2
STATE = ("x", "y", "psi", "v_y", "r")


@dataclass(frozen=True, kw_only=True)
class SingleTrack:
    """Parameters of the dynamic single-track car.

    The defaults are a mid-size passenger car on dry asphalt, with the kinematic bicycle's
    2.7 m wheelbase: 1500 kg, 2250 kg m^2, the centre of gravity 1.2 m behind the front axle
    (55 % of the weight on the front axle), 80 and 100 kN/rad of cornering stiffness per axle
    and a friction coefficient of 1. Its understeer gradient is 3.75 mrad per m/s^2 (2.1 degrees
    per g), in the range of road cars.

    Attributes
    ----------
    mass : m (kg).
    yaw_inertia : I_z (kg m^2).
    l_f, l_r : distances from the centre of gravity to the front and rear axles (m); they sum
        to the wheelbase.
    c_f, c_r : cornering stiffness of the front and rear axle (N/rad).
    mu : tyre-road friction coefficient; an axle's force saturates at mu F_z.
    v_kinematic : below this speed (m/s) the car moves as the kinematic bicycle.
    substeps : RK4 sub-steps per sampling period.
    """

    mass: float = 1500.0
    yaw_inertia: float = 2250.0
    l_f: float = 1.2
    l_r: float = 1.5
    c_f: float = 80_000.0
    c_r: float = 100_000.0
    mu: float = 1.0
    v_kinematic: float = 2.0
    substeps: int = 4

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name == "substeps":
                object.__setattr__(self, f.name, integer(self.substeps, "car.substeps", 1))
            else:
                object.__setattr__(self, f.name, number(getattr(self, f.name), f"car.{f.name}",
                                                        low=0.0, low_open=True))

    @property
    def wheelbase(self) -> float:
        return self.l_f + self.l_r

    @property
    def understeer_gradient(self) -> float:
        """K = (m / L) (l_r / C_f - l_f / C_r), rad per m/s^2 of lateral acceleration."""
        return self.mass / self.wheelbase * (self.l_r / self.c_f - self.l_f / self.c_r)

    @property
    def axle_loads(self) -> tuple[float, float]:
        """Static normal forces (F_zf, F_zr) in N."""
        w = self.mass * G / self.wheelbase
        return w * self.l_r, w * self.l_f

    # the truth model's contract (docs/plugins.md), which a user's car keeps too
    def start(self, z0: np.ndarray, u0: np.ndarray) -> np.ndarray:
        """(..., 5) states at poses z0 (..., 3), in steady state for the inputs u0 (..., 2)."""
        return start(z0, u0, self)

    def step(self, s: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """One sampling period dt (s) from states s (..., 5), inputs u (..., 2) held."""
        return step(s, u, dt, self)

    def rear_slip(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The rear axle's side slip (rad) (...,) of states s (..., 5), inputs u (..., 2)."""
        return rear_slip(s, u, self)


def tyre_force(alpha: np.ndarray, c: float, f_max: float) -> np.ndarray:
    """Lateral force (N) at slip angle ``alpha`` (rad): ``f_max tanh(c alpha / f_max)``."""
    return f_max * np.tanh(c * alpha / f_max)


def _blend(v: np.ndarray, p: SingleTrack) -> np.ndarray:
    """Weight of the dynamic model: 0 below v_kinematic, 1 above twice it, smoothstep between."""
    s = np.clip(v / p.v_kinematic - 1.0, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def lateral_rates(v_y: np.ndarray, r: np.ndarray, v: np.ndarray, delta: np.ndarray,
                  p: SingleTrack) -> tuple[np.ndarray, np.ndarray]:
    """(dv_y/dt, dr/dt) of the single-track equations at speed ``max(v, v_kinematic)``."""
    return _lateral(v_y, r, np.maximum(v, p.v_kinematic), delta, np.cos(delta), p)


def _lateral(v_y: np.ndarray, r: np.ndarray, vx: np.ndarray, delta: np.ndarray,
             cos_delta: np.ndarray, p: SingleTrack) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lateral_rates` at the speed ``vx`` it integrates at, with ``cos(delta)`` given."""
    fzf, fzr = p.axle_loads
    a_f = delta - (v_y + p.l_f * r) / vx
    a_r = -(v_y - p.l_r * r) / vx
    f_yf = tyre_force(a_f, p.c_f, p.mu * fzf) * cos_delta
    f_yr = tyre_force(a_r, p.c_r, p.mu * fzr)
    return (f_yf + f_yr) / p.mass - vx * r, (p.l_f * f_yf - p.l_r * f_yr) / p.yaw_inertia


class _Held(NamedTuple):
    """What inputs u (..., 2), held over a sampling period, give :func:`derivatives`: made
    once a period, where RK4 evaluates the derivatives four times a sub-step. Each (...)."""

    v: np.ndarray
    """V, the speed input (m/s)."""
    w: np.ndarray
    """The dynamic model's weight (:func:`_blend`)."""
    turn: np.ndarray
    """``(1 - w) V tan(delta) / L``: the kinematic bicycle's share of the yaw rate."""
    vx: np.ndarray
    """``max(V, v_kinematic)``, the speed the lateral states are integrated at."""
    delta: np.ndarray
    """The steering angle (rad)."""
    cos_delta: np.ndarray
    """Its cosine."""


def _held(u: np.ndarray, p: SingleTrack) -> _Held:
    v, delta = u[..., 0], u[..., 1]
    w = _blend(v, p)
    return _Held(v, w, (1 - w) * v * np.tan(delta) / p.wheelbase,
                 np.maximum(v, p.v_kinematic), delta, np.cos(delta))


def derivatives(s: np.ndarray, u: np.ndarray, p: SingleTrack) -> np.ndarray:
    """Continuous dynamics ``ds/dt``. s: (..., 5), u: (..., 2) -> (..., 5)."""
    return _rates(s, _held(u, p), p)


def _rates(s: np.ndarray, held: _Held, p: SingleTrack) -> np.ndarray:
    """:func:`derivatives` at states s (..., 5) with what the inputs give (:func:`_held`)."""
    psi, v_y, r = s[..., 2], s[..., 3], s[..., 4]
    v, w = held.v, held.w
    r_eff = w * r + held.turn
    lat = w * (v_y - p.l_r * r)  # lateral speed of the rear axle; 0 for the kinematic bicycle
    c, sn = np.cos(psi), np.sin(psi)
    dv_y, dr = _lateral(v_y, r, held.vx, held.delta, held.cos_delta, p)
    # filled column by column: np.stack costs twice that on the small batches of a time step
    out = np.empty(np.shape(r_eff) + (5,))
    out[..., 0], out[..., 1] = v * c - lat * sn, v * sn + lat * c
    out[..., 2], out[..., 3], out[..., 4] = r_eff, dv_y, dr
    return out


def step(s: np.ndarray, u: np.ndarray, dt: float, p: SingleTrack,
         substeps: int | None = None) -> np.ndarray:
    """One sampling period of RK4 sub-steps, the input held. s: (..., 5), u: (..., 2)."""
    n = p.substeps if substeps is None else substeps
    h = dt / n
    held = _held(u, p)
    for _ in range(n):
        k1 = _rates(s, held, p)
        k2 = _rates(s + 0.5 * h * k1, held, p)
        k3 = _rates(s + 0.5 * h * k2, held, p)
        k4 = _rates(s + h * k3, held, p)
        s = s + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s


def start(z0: np.ndarray, u0: np.ndarray, p: SingleTrack) -> np.ndarray:
    """(..., 5) states at poses z0 (..., 3), in steady state for the first inputs u0 (..., 2)."""
    v_y, r = steady_state(u0[..., 0], u0[..., 1], p)
    return np.concatenate([z0, v_y[..., None], r[..., None]], axis=-1)


def simulate(z0: np.ndarray, u: np.ndarray, dt: float, p: Car,
             process_sigma: np.ndarray | Sequence[float] | None = None,
             rng: np.random.Generator | None = None,
             lateral_sigma: Sequence[float] | None = None) -> np.ndarray:
    """Roll the car forward over known inputs, as :func:`lbo.sim.vehicle.simulate` does.

    Parameters
    ----------
    p : the car: a SingleTrack, or any car that keeps :class:`lbo.sim.truth.Car`.
    z0 : (B, 3) initial poses; the lateral states start as ``p.start`` sets them.
    u : (B, T, 2) inputs; ``u[:, k]`` moves ``s_k`` to ``s_{k+1}``.
    process_sigma : (3,) standard deviations of the noise added to x, y, psi after each step.
    lateral_sigma : (2,) standard deviations of the disturbances added to v_y and r after each
        step (:func:`lateral_noise`), drawn after the process noise.

    Returns
    -------
    (B, T, 5) states s_0 .. s_{T-1}; psi continuous.
    """
    b, t = u.shape[:2]
    s = np.empty((b, t, 5))
    s[:, 0] = p.start(z0, u[:, 0])
    w = np.zeros((b, max(t - 1, 0), 5))
    if process_sigma is not None:
        assert rng is not None, "process_sigma needs an rng"
        w[..., :3] = rng.standard_normal(w[..., :3].shape) * np.asarray(process_sigma)
    w[..., 3:] = lateral_noise(rng, w.shape[:2], lateral_sigma)
    for k in range(t - 1):  # sequential in time, vectorised over the batch
        s[:, k + 1] = p.step(s[:, k], u[:, k], dt) + w[:, k]
    return s


def lateral_noise(rng: np.random.Generator | None, shape: tuple[int, ...],
                  sigma: Sequence[float] | None) -> np.ndarray:
    """(*shape, 2) white disturbances of v_y and r, standard deviations ``sigma`` (2,)
    (:attr:`lbo.sim.truth.Truth.lateral_sigma`). Zeros where there are none (None, or both 0),
    and then ``rng`` is not drawn: the sets drawn without them keep their draws."""
    if sigma is None or not np.any(np.asarray(sigma) > 0):
        return np.zeros((*shape, 2))
    assert rng is not None, "lateral_sigma needs an rng"
    return rng.standard_normal((*shape, 2)) * np.asarray(sigma)


def steady_state(v: np.ndarray, delta: np.ndarray, p: SingleTrack
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form steady-state (v_y, r) of the linear tyre model (small slip, cos delta = 1).

        r = v delta / (L + K v^2),   rear slip a_r = m a_y l_f / (L C_r),   v_y = l_r r - v a_r,

    with ``a_y = v r``; below v_kinematic the kinematic bicycle's ``r = v tan(delta) / L`` and
    no rear slip. Shapes broadcast.
    """
    v = np.asarray(v, dtype=float)
    delta = np.asarray(delta, dtype=float)
    vx = np.maximum(v, p.v_kinematic)
    r = vx * delta / (p.wheelbase + p.understeer_gradient * vx**2)
    a_r = p.mass * vx * r * p.l_f / (p.wheelbase * p.c_r)
    return p.l_r * r - vx * a_r, r


def rear_slip(s: np.ndarray, u: np.ndarray, p: SingleTrack) -> np.ndarray:
    """Angle (rad) between the rear axle's velocity and the heading: the rear side slip.

    s: (..., 5), u: (..., 2) -> (...,). Zero for the kinematic bicycle."""
    return np.arctan2(_blend(u[..., 0], p) * (s[..., 3] - p.l_r * s[..., 4]),
                      np.maximum(u[..., 0], 1e-9))
