"""Side slip and yaw rate from the sensors a car has: the linear single-track Kalman filter.

The states no sensor gives: the side-slip angle beta (and with it the lateral velocity
v_y = vx tan(beta)) beside the yaw rate r. The inputs are the speed vx and the road wheels'
steering delta; the measurements the yaw rate and the lateral acceleration at the centre of
gravity. The model is the linear single-track car (:class:`lbo.sim.dynamic.SingleTrack`'s
parameters; its tyres linear in their slip, which holds away from the limit), its
continuous equations

    beta' = -(C_f + C_r) / (m vx) beta - (1 + (l_f C_f - l_r C_r) / (m vx^2)) r
            + C_f / (m vx) delta
    r'    = -(l_f C_f - l_r C_r) / I_z beta - (l_f^2 C_f + l_r^2 C_r) / (I_z vx) r
            + l_f C_f / I_z delta
    a_y   = -(C_f + C_r) / m beta - (l_f C_f - l_r C_r) / (m vx) r + C_f / m delta

taken one Euler step of dt at a time, as the MBDS side-slip repository's reference filter
(``BetaStanfordLinear.m``) takes them: the prediction to row k from row k-1's speed and
steering, the update with row k's. The process noise is the steering's noise passed through
the input's column (Q = B q^2 B^T).

:func:`kinematic_beta` is the kinematic bicycle's side slip at the centre of gravity, which
assumes no tyre slips: the guess that needs no parameter but the axles'.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lbo.core.checks import number
from lbo.core.errors import LboError
from lbo.filters.update import joseph_update
from lbo.sim.dynamic import SingleTrack, lateral_rates

STATE = ("beta", "r")
"""The filter's states, in the order ``x`` holds them; ``y`` holds [ay, r]."""


@dataclass(frozen=True)
class LateralNoise:
    """Noise of the linear single-track filter (standard deviations).

    Attributes
    ----------
    delta : the steering input's noise (rad) that drives the process noise.
    ay : the lateral acceleration's noise (m/s^2).
    r : the yaw rate's noise (rad/s).
    """

    delta: float
    ay: float
    r: float

    def __post_init__(self) -> None:
        for name in ("delta", "ay", "r"):
            number(getattr(self, name), f"noise.{name}", low=0.0, low_open=True)

    @classmethod
    def of(cls, vx: np.ndarray, delta: np.ndarray, y: np.ndarray,
           process_gain: float = 1000.0) -> LateralNoise:
        """The noise read off a span of a log (vx (T,) is unused but for its length), as the
        reference filter reads it: each channel's high-frequency part (the first difference,
        whose variance is twice a white noise's), the steering's times ``process_gain`` (the
        reference scales its by 1000: the input's own noise is far below what the linear
        model misses). delta (T,), y (T, 2) [ay, r]."""
        if not (len(vx) == len(delta) == len(y)) or len(y) < 3:
            raise LboError("LateralNoise.of needs vx, delta (T,) and y (T, 2) of one length, "
                           "at least 3 rows")

        def white(v: np.ndarray) -> float:
            return float(np.std(np.diff(v)) / np.sqrt(2.0))

        return cls(delta=white(delta) * process_gain, ay=white(y[:, 0]), r=white(y[:, 1]))


@dataclass(frozen=True)
class LateralEstimate:
    """What the lateral filter gives for each row: ``x`` (..., T, 2) [beta rad, r rad/s] and
    its covariance ``P`` (..., T, 2, 2)."""

    x: np.ndarray
    P: np.ndarray

    @property
    def beta(self) -> np.ndarray:
        """(..., T) side slip (rad)."""
        return self.x[..., 0]

    @property
    def r(self) -> np.ndarray:
        """(..., T) yaw rate (rad/s)."""
        return self.x[..., 1]

    def vy(self, vx: np.ndarray) -> np.ndarray:
        """(..., T) lateral velocity (m/s) at the speeds vx (..., T)."""
        return vx * np.tan(self.beta)


def kinematic_beta(delta: np.ndarray, car: SingleTrack) -> np.ndarray:
    """The kinematic bicycle's side slip at the centre of gravity (rad),
    atan(l_r tan(delta) / L), for road-wheel angles delta (any shape)."""
    return np.arctan(car.l_r * np.tan(delta) / car.wheelbase)


def _model(vx: np.ndarray, car: SingleTrack, dt: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The discrete model at speeds vx (...): A (..., 2, 2), B (..., 2), C (..., 2, 2),
    D (2,)."""
    m, iz, lf, lr, cf, cr = car.mass, car.yaw_inertia, car.l_f, car.l_r, car.c_f, car.c_r
    A = np.empty((*vx.shape, 2, 2))
    A[..., 0, 0] = 1 - dt * (cf + cr) / (m * vx)
    A[..., 0, 1] = -dt * (1 + (lf * cf - lr * cr) / (m * vx**2))
    A[..., 1, 0] = -dt * (lf * cf - lr * cr) / iz
    A[..., 1, 1] = 1 - dt * (lf**2 * cf + lr**2 * cr) / (iz * vx)
    B = np.stack([dt * cf / (m * vx), np.full(vx.shape, dt * lf * cf / iz)], axis=-1)
    C = np.zeros((*vx.shape, 2, 2))
    C[..., 0, 0] = -(cf + cr) / m
    C[..., 0, 1] = -(lf * cf - lr * cr) / (m * vx)
    C[..., 1, 1] = 1.0
    D = np.array([cf / m, 0.0])
    return A, B, C, D


Model = Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""(x (G, 2), row k) -> (value (G, 2), Jacobian in x (G, 2, 2), derivative in delta (G, 2)):
the step from row k to the next on row k's speed and steering, or the measurements [ay, r]
at row k."""


def linear_single_track(vx: np.ndarray, delta: np.ndarray, y: np.ndarray, car: SingleTrack,
                        noise: LateralNoise, dt: float, p0: float = 1e4,
                        start: LateralEstimate | None = None) -> LateralEstimate:
    """The linear single-track Kalman filter over G logs at once.

    Parameters
    ----------
    vx : (G, T) or (T,) speed (m/s), above zero.
    delta : like vx, road-wheel steering (rad).
    y : (G, T, 2) or (T, 2) measurements [ay m/s^2, r rad/s]; a NaN is a channel not held.
    car : the car's parameters.
    noise : :class:`LateralNoise`.
    dt : sampling period (s).
    p0 : the first row's variance of each state (the state starts at zero, straight ahead).
    start : row 0's state and covariance in place of zero and p0, x (G, 2) or (2,) and P
        (G, 2, 2) or (2, 2): a filter carried on from an earlier call (a stream's step is a
        call on rows k-1 and k, started from row k-1's estimate).

    Returns
    -------
    LateralEstimate with x (G, T, 2) (or (T, 2)) and P (G, T, 2, 2) (or (T, 2, 2)); row 0 is
    the starting prior.
    """
    vx, delta, y, single = _inputs("linear_single_track", vx, delta, y)
    A, B, C, D = _model(vx, car, dt)  # every row's at once: (G, T, ...)

    def step(x: np.ndarray, k: int):
        return np.einsum("gij,gj->gi", A[:, k], x) + B[:, k] * delta[:, k, None], A[:, k], B[:, k]

    def measure(x: np.ndarray, k: int):
        return (np.einsum("gij,gj->gi", C[:, k], x) + D * delta[:, k, None], C[:, k],
                np.broadcast_to(D, x.shape))

    return _filter(y, single, noise, p0, step, measure, start)


def nonlinear_single_track(vx: np.ndarray, delta: np.ndarray, y: np.ndarray, car: SingleTrack,
                           noise: LateralNoise, dt: float, p0: float = 1e4) -> LateralEstimate:
    """The single-track EKF with tyres that saturate: each axle's force
    ``mu F_z tanh(C alpha / (mu F_z))`` (:func:`lbo.sim.dynamic.lateral_rates`, lbo's car that
    slips), linear with the cornering stiffness C at small slip, capped at ``car.mu`` times
    the axle's load. Arguments and result as :func:`linear_single_track`; the Jacobians by
    central differences (the model is smooth), the steering's noise through the model's
    derivative in delta as in the linear filter."""
    def rates(x: np.ndarray, v: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(beta', r') (G, 2) and the lateral acceleration (G,) at states x (G, 2)."""
        v_y = v * np.tan(x[:, 0])
        dv_y, dr = lateral_rates(v_y, x[:, 1], v, d, car)
        return np.stack([v * dv_y / (v**2 + v_y**2), dr], axis=-1), dv_y + v * x[:, 1]

    vx, delta, y, single = _inputs("nonlinear_single_track", vx, delta, y)

    def step(x: np.ndarray, k: int):
        def f(xx: np.ndarray, dd: np.ndarray) -> np.ndarray:
            return xx + dt * rates(xx, vx[:, k], dd)[0]
        return f(x, delta[:, k]), *_derivatives(f, x, delta[:, k])

    def measure(x: np.ndarray, k: int):
        def h(xx: np.ndarray, dd: np.ndarray) -> np.ndarray:
            return np.stack([rates(xx, vx[:, k], dd)[1], xx[:, 1]], axis=-1)
        return h(x, delta[:, k]), *_derivatives(h, x, delta[:, k])

    return _filter(y, single, noise, p0, step, measure)


def _derivatives(f: Callable[[np.ndarray, np.ndarray], np.ndarray], x: np.ndarray,
                 d: np.ndarray, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of f(x (G, 2), d (G,)) -> (G, 2): in x (G, 2, 2), in d (G, 2)."""
    cols = [(f(x + e, d) - f(x - e, d)) / (2 * eps) for e in np.eye(2) * eps]
    return np.stack(cols, axis=-1), (f(x, d + eps) - f(x, d - eps)) / (2 * eps)


def _inputs(name: str, vx: np.ndarray, delta: np.ndarray, y: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """vx, delta (G, T), y (G, T, 2) as floats, and whether one log (T,) was given; checked."""
    single = np.ndim(vx) == 1
    vx, delta, y = (np.atleast_2d(np.asarray(vx, float)), np.atleast_2d(np.asarray(delta, float)),
                    np.asarray(y, float))
    if single:
        y = y[None]
    g, t = vx.shape
    if delta.shape != (g, t) or y.shape != (g, t, 2):
        raise LboError(f"{name} needs vx and delta (G, T), y (G, T, 2); got "
                       f"{vx.shape}, {delta.shape}, {y.shape}")
    if not (vx > 0).all():
        raise LboError("vx: expected speeds above 0 m/s (the model divides by them), got "
                       f"{float(np.nanmin(vx)):g}")
    return vx, delta, y, single


def _filter(y: np.ndarray, single: bool, noise: LateralNoise, p0: float, step: Model,
            measure: Model, start: LateralEstimate | None = None) -> LateralEstimate:
    """The Kalman filter both models share over y (G, T, 2): the prediction to row k from
    row k-1's speed and steering, the update with row k's (a NaN channel is not held)."""
    g, t = y.shape[:2]
    R = np.diag([noise.ay**2, noise.r**2])
    xs, Ps = np.zeros((g, t, 2)), np.zeros((g, t, 2, 2))
    if start is None:
        x, P = np.zeros((g, 2)), np.broadcast_to(np.eye(2) * p0, (g, 2, 2)).copy()
    else:
        x = np.broadcast_to(np.asarray(start.x, float), (g, 2)).copy()
        P = np.broadcast_to(np.asarray(start.P, float), (g, 2, 2)).copy()
    xs[:, 0], Ps[:, 0] = x, P
    for k in range(1, t):  # a recursive filter: one step per row, every log at once
        x, F, B = step(x, k - 1)
        P = F @ P @ F.transpose(0, 2, 1) + noise.delta**2 * B[:, :, None] * B[:, None, :]
        h, H, _ = measure(x, k)
        held = np.isfinite(y[:, k])
        x, P, *_ = joseph_update(x, P, np.where(held, y[:, k] - h, 0.0), H, R, held)
        xs[:, k], Ps[:, k] = x, P
    if single:
        return LateralEstimate(xs[0], Ps[0])
    return LateralEstimate(xs, Ps)
