"""Simulated real sensors: a single-antenna GNSS receiver and a yaw-rate gyro.

The paper's sensor is a full pose at every step with white noise. A production car has a
receiver that fixes its position (no heading) at 1-10 Hz, a little late, with errors that
wander, and reports how accurate it thinks each fix is; and an ESC gyro whose bias wanders.
:func:`sense` draws these channels from a true trajectory, each with its own settings
(:class:`Channel`): rate, latency, white noise and Gauss-Markov drift.

- position ``x_m, y_m`` (m): the truth ``latency`` s before the row, plus alpha times (white
  noise + drift), at ``rate`` Hz; no ``psi_m`` (one antenna);
- its reported accuracy ``sx_m, sy_m``: alpha times the error's 1-sigma
  ``sqrt(white^2 + drift^2)``, times a log-normal factor of spread ``reported_spread`` (a
  receiver's estimate of its own accuracy tracks the true error's scale, not each error);
- velocity ``ve_m, vn_m`` (m/s) with ``sv_m``: the rear axle's velocity, along the heading
  turned by its side slip (``slip``: 0 for the kinematic bicycle, the car that slips' rear
  slip), at the same latency, noise and rate (a receiver gives both from one solution);
- gyro ``r_m`` (rad/s, counter-clockwise): the true yaw rate, plus a bias that starts at
  N(0, ``gyro_bias^2``) and random-walks at ``gyro_walk`` rad/s/sqrt(s), plus white noise
  and drift; at every step unless its rate is set. alpha scales the receiver's errors, not
  the gyro's.

Every channel is drawn from its own generator (``rng`` spawned), vectorised over G
trajectories. ``python -m lbo.simulate receiver=single_antenna`` writes them into a log;
the paper's data sets do not use them and stay byte for byte as they are.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.checks import number
from lbo.core.errors import LboError
from lbo.sim.truth import gauss_markov


@dataclass(frozen=True, kw_only=True)
class Channel:
    """One sensor channel's timing and errors (at alpha = 1 for the receiver's).

    rate : Hz, or None: every step.
    latency : s from the instant a sample is of to the row it is logged at (>= 0).
    white : 1-sigma of its white noise.
    drift : stationary 1-sigma of its first-order Gauss-Markov drift.
    tau : the drift's correlation time (s).
    """

    rate: float | None = None
    latency: float = 0.0
    white: float = 0.0
    drift: float = 0.0
    tau: float = 60.0

    def check(self, name: str, dt: float) -> None:
        if self.rate is not None:
            number(self.rate, f"receiver.{name}.rate", low=0.0, high=1 / dt, low_open=True,
                   form=f"null (every step) or a rate in Hz in (0, {1 / dt:g}]")
        number(self.latency, f"receiver.{name}.latency", low=0.0, high=10.0)
        number(self.white, f"receiver.{name}.white", low=0.0)
        number(self.drift, f"receiver.{name}.drift", low=0.0)
        number(self.tau, f"receiver.{name}.tau", low=0.0, low_open=True)

    @property
    def sigma(self) -> float:
        """1-sigma of its whole error (white and drift)."""
        return float(np.hypot(self.white, self.drift))


@dataclass(frozen=True, kw_only=True)
class ReceiverSpec:
    """A single-antenna receiver and a gyro (see the module's docstring).

    The defaults: a single-frequency receiver in the open at 1 Hz (0.3 m white, 0.5 m drift
    over a minute, 50 ms late; velocity to 0.05 m/s) and a consumer-grade gyro (0.005 rad/s
    white at 50 Hz, bias 0.005 rad/s walking at 1e-4 rad/s/sqrt(s)).
    """

    position: Channel = field(default_factory=lambda: Channel(rate=1.0, latency=0.05, white=0.3,
                                                              drift=0.5, tau=60.0))
    velocity: Channel = field(default_factory=lambda: Channel(rate=1.0, latency=0.05, white=0.05,
                                                              drift=0.0, tau=60.0))
    gyro: Channel = field(default_factory=lambda: Channel(rate=None, latency=0.0, white=0.005,
                                                          drift=0.0, tau=60.0))
    gyro_bias: float = 0.005
    gyro_walk: float = 1e-4
    reported_spread: float = 0.2
    speed_scale: float = 1.0
    """The speed sensor's factor: the log's ``V`` is the car's speed times it (a wheel or CAN
    speed reads a percent or two off; 1: exact)."""

    @classmethod
    def from_cfg(cls, cfg: Any, dt: float) -> ReceiverSpec:
        """The spec of the Hydra group ``receiver``, each field checked in one line."""
        c = dict(cfg)
        channels = {}
        for name in ("position", "velocity", "gyro"):
            sub = dict(c.pop(name, {}) or {})
            unknown = [k for k in sub if k not in Channel.__dataclass_fields__]
            if unknown:
                raise LboError(f"receiver.{name}.{unknown[0]}: not a field; accepted: "
                               f"{', '.join(Channel.__dataclass_fields__)}")
            channels[name] = Channel(**{**vars(getattr(cls(), name)), **sub})
            channels[name].check(name, dt)
        c.pop("name", None)
        unknown = [k for k in c if k not in cls.__dataclass_fields__]
        if unknown:
            raise LboError(f"receiver.{unknown[0]}: not a field; accepted: name, "
                           f"{', '.join(cls.__dataclass_fields__)}")
        for k in ("gyro_bias", "gyro_walk", "reported_spread"):
            if k in c:
                number(c[k], f"receiver.{k}", low=0.0)
        if "speed_scale" in c:
            number(c["speed_scale"], "receiver.speed_scale", low=0.5, high=2.0)
        return cls(position=channels["position"], velocity=channels["velocity"],
                   gyro=channels["gyro"], **c)


SIGMA_FLOOR = 1e-3
"""Smallest accuracy reported (m, m/s): a receiver never claims to be exact (alpha = 0)."""
COLUMNS = ("x_m", "y_m", "psi_m", "sx_m", "sy_m", "ve_m", "vn_m", "sv_m", "r_m")
"""The columns :func:`sense` writes (``psi_m`` all NaN: one antenna has no heading)."""


def _delayed(a: np.ndarray, latency: float, dt: float) -> np.ndarray:
    """a (G, T, ...) as it was ``latency`` s before each row (linear interpolation along T;
    the first row's value before the log began)."""
    t = a.shape[1]
    f = np.clip(np.arange(t) - latency / dt, 0.0, t - 1)
    i0 = np.floor(f).astype(np.int64)
    i1 = np.minimum(i0 + 1, t - 1)
    w = (f - i0).reshape((1, t) + (1,) * (a.ndim - 2))
    return a[:, i0] * (1 - w) + a[:, i1] * w


def _rows(rate: float | None, t: int, dt: float) -> np.ndarray:
    """(T,) bool, the rows a channel at ``rate`` Hz holds a sample in (the first one's)."""
    if rate is None:
        return np.ones(t, bool)
    return np.arange(t) % max(1, int(round(1.0 / (rate * dt)))) == 0


def _error(ch: Channel, shape: tuple[int, ...], dt: float, rng: np.random.Generator
           ) -> np.ndarray:
    """White noise plus Gauss-Markov drift (shape (G, T, ...)) of a channel at alpha 1."""
    out = ch.white * rng.standard_normal(shape)
    if ch.drift > 0:
        out += gauss_markov(shape, dt, ch.tau, ch.drift, rng)
    return out


def gyro_bias(shape: tuple[int, int], dt: float, spec: ReceiverSpec,
              rng: np.random.Generator) -> np.ndarray:
    """(G, T) gyro bias: N(0, gyro_bias^2) at the first row, then a random walk whose
    increments over ``s`` seconds have variance ``gyro_walk^2 s``."""
    b0 = spec.gyro_bias * rng.standard_normal((shape[0], 1))
    steps = spec.gyro_walk * np.sqrt(dt) * rng.standard_normal(shape)
    steps[:, 0] = 0.0
    return b0 + np.cumsum(steps, axis=1)


def sense(z: np.ndarray, u: np.ndarray, dt: float, spec: ReceiverSpec,
          alpha: float | np.ndarray, rng: np.random.Generator,
          slip: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The receiver's and gyro's channels of G true trajectories.

    z : (G, T, 3) true ``[x, y, psi]``, T >= 2; u : (G, T, 2) true ``[V, delta]``; dt : s;
    alpha : noise scale of the receiver, one or (G,); rng : the generator the channels'
    own are spawned from; slip : (G, T) the rear axle's side slip (rad), or None (none): its
    velocity is ``V / cos(slip)`` along ``psi + slip``.

    Returns :data:`COLUMNS` -> (G, T) arrays, NaN in the rows a channel does not hold.
    Also ``"gyro_bias"`` (G, T): the bias the gyro had (for scoring a filter's estimate).
    """
    z, u = np.asarray(z, float), np.asarray(u, float)
    g, t = z.shape[:2]
    a = np.reshape(np.broadcast_to(np.asarray(alpha, float), (g,)), (g, 1))
    r_pos, r_vel, r_gyro, r_bias, r_rep = rng.spawn(5)
    pos = _delayed(z[..., :2], spec.position.latency, dt)
    pos = pos + a[..., None] * _error(spec.position, (g, t, 2), dt, r_pos)
    lean = np.zeros((g, t)) if slip is None else np.broadcast_to(np.asarray(slip, float), (g, t))
    course = z[..., 2] + lean
    vel = (u[..., :1] / np.cos(lean)[..., None]) * np.stack([np.cos(course), np.sin(course)],
                                                            axis=-1)
    vel = _delayed(vel, spec.velocity.latency, dt)
    vel = vel + a[..., None] * _error(spec.velocity, (g, t, 2), dt, r_vel)
    # the yaw rate over each step (the last one repeated), heading on its branch
    turn = wrap_angle(np.diff(z[..., 2], axis=1)) / dt
    rate = np.concatenate([turn, turn[:, -1:]], axis=1)
    bias = gyro_bias((g, t), dt, spec, r_bias)
    gyro = _delayed(rate, spec.gyro.latency, dt) + bias + _error(spec.gyro, (g, t), dt, r_gyro)
    spread = np.exp(spec.reported_spread * r_rep.standard_normal((g, t))
                    - 0.5 * spec.reported_spread**2)
    fix, fast, every = (_rows(c.rate, t, dt) for c in (spec.position, spec.velocity, spec.gyro))
    nan = np.full((g, t), np.nan)
    out = {
        "x_m": np.where(fix, pos[..., 0], nan), "y_m": np.where(fix, pos[..., 1], nan),
        "psi_m": nan.copy(),
        "sx_m": np.where(fix, np.maximum(a * spec.position.sigma * spread, SIGMA_FLOOR), nan),
        "ve_m": np.where(fast, vel[..., 0], nan), "vn_m": np.where(fast, vel[..., 1], nan),
        "sv_m": np.where(fast, np.maximum(a * spec.velocity.sigma, SIGMA_FLOOR), nan),
        "r_m": np.where(every, gyro, nan), "gyro_bias": bias,
    }
    out["sy_m"] = out["sx_m"].copy()
    return out
