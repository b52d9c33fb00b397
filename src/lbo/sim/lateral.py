"""Simulated runs of the kind the MBDS side-slip run is: cars driven through corners up to and
past the limit of their tyres, with what a car measures and the side slip an INS would give.

:func:`simulate` drives ``n`` cars at once, each its own: the published car
(:data:`lbo.sim.sideslip.CAR`) with its mass, yaw inertia, axle positions and cornering
stiffness each scaled by a factor drawn in ``1 +- spread``, and a friction drawn from ``mu``.
Each is lbo's car that slips (:mod:`lbo.sim.dynamic`: RK4, tyres that saturate at ``mu F_z``).

- Each car understeers at least half as much as the published one (a car that oversteers
  spins above its critical speed).
- The speed vx wanders between ``speed`` bounds (two slow sines, as the real run's, whose
  power lies under 0.07 Hz).
- The steering asks for a lateral acceleration made of four sines of 0.02-0.15 Hz (the real
  run's steering holds 90% of its power under 0.15 Hz), peaking at ``demand`` times the car's
  friction times g: the steering the linear car would need for it, so a demand above 1 drives
  the tyres past their limit, as the real driver did.
- The measurements are the true lateral acceleration at the centre of gravity and the yaw
  rate, each with white noise (``sigma_ay``, ``sigma_r``); the steering is read exactly.

The frames have the real run's columns (:data:`lbo.sim.sideslip.COLUMNS`' ``t``, ``vx``,
``delta``, ``ay_m``, ``r_m``, ``vy``, ``beta``), so an observer reads them as it reads the
real run (:func:`lbo.sim.sideslip.observed`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from lbo.core.checks import integer, number, require
from lbo.sim import dynamic
from lbo.sim.dynamic import G, SingleTrack
from lbo.sim.sideslip import CAR, DT

SCALED = ("mass", "yaw_inertia", "l_f", "l_r", "c_f", "c_r")
"""The car's parameters each drawn as the published value times a factor in 1 +- spread."""


@dataclass(frozen=True, kw_only=True)
class Settings:
    """What :func:`simulate` draws (checked: one line naming the field ``data.<name>``)."""

    n: int = 32
    duration: float = 60.0
    spread: float = 0.2
    mu: tuple[float, float] = (0.9, 1.4)
    speed: tuple[float, float] = (16.0, 61.0)
    demand: tuple[float, float] = (0.5, 1.3)
    sigma_ay: float = 1.0
    sigma_r: float = 0.005

    def __post_init__(self) -> None:
        integer(self.n, "data.n", 1)
        number(self.duration, "data.duration", low=1.0, form="a duration >= 1 s")
        number(self.spread, "data.spread", low=0.0, high=0.5,
               form="a share in [0, 0.5] (each parameter times 1 +- spread)")
        for name, low in (("mu", 0.0), ("speed", 5.0), ("demand", 0.0)):
            pair = getattr(self, name)
            require(len(pair) == 2 and low < pair[0] <= pair[1], f"data.{name}",
                    f"[low, high] with {low} < low <= high", list(pair))
        number(self.sigma_ay, "data.sigma_ay", low=0.0)
        number(self.sigma_r, "data.sigma_r", low=0.0)


def _cars(rng: np.random.Generator, s: Settings) -> list[SingleTrack]:
    """``s.n`` cars drawn around the published one, each understeering at least half as much
    (drawn independently, the axles' stiffness and positions can make a car that oversteers,
    which spins above its critical speed: no driver at the limit keeps such a car)."""
    cars: list[SingleTrack] = []
    while len(cars) < s.n:
        factors = rng.uniform(1 - s.spread, 1 + s.spread, (s.n, len(SCALED)))
        mus = rng.uniform(*s.mu, s.n)
        for row, m in zip(factors, mus):
            scaled: dict[str, Any] = {k: float(getattr(CAR, k) * f) for k, f in zip(SCALED, row)}
            car = dataclasses.replace(CAR, mu=float(m), **scaled)
            if car.understeer_gradient >= 0.5 * CAR.understeer_gradient and len(cars) < s.n:
                cars.append(car)
    return cars


def _batch(cars: list[SingleTrack]) -> SingleTrack:
    """One :class:`SingleTrack` whose fields are (n,) arrays of the cars', for the equations
    that read only fields and properties (:func:`lbo.sim.dynamic.lateral_rates`,
    :func:`~lbo.sim.dynamic.steady_state`), so that they run every car at once. Each car passed
    the scalar checks; the batch skips them."""
    batch = object.__new__(SingleTrack)
    for f in dataclasses.fields(SingleTrack):
        object.__setattr__(batch, f.name, np.array([getattr(c, f.name) for c in cars]))
    return batch


def _sines(rng: np.random.Generator, t: np.ndarray, n: int, k: int, low: float, high: float
            ) -> np.ndarray:
    """(n, T) sums of k sines of frequencies in [low, high] Hz and random phases, each row
    scaled to a peak of 1."""
    f = rng.uniform(low, high, (n, k, 1))
    phase = rng.uniform(0, 2 * np.pi, (n, k, 1))
    amp = rng.uniform(0.3, 1.0, (n, k, 1))
    s = (amp * np.sin(2 * np.pi * f * t + phase)).sum(axis=1)
    return s / np.abs(s).max(axis=1, keepdims=True)


def simulate(settings: Settings, seed: int) -> list[pd.DataFrame]:
    """``settings.n`` runs of ``settings.duration`` s at the real run's 100 Hz, each a frame
    with columns ``t, vx, delta, ay_m, r_m, vy, beta`` (T rows), and the car each was
    driven with in ``frame.attrs["car"]`` (a dict of :class:`SingleTrack`'s fields)."""
    rng = np.random.default_rng(seed)
    s = settings
    cars = _cars(rng, s)
    t = np.arange(int(round(s.duration / DT))) * DT
    mid, half = (s.speed[0] + s.speed[1]) / 2, (s.speed[1] - s.speed[0]) / 2
    vx = mid + half * _sines(rng, t, s.n, 2, 0.005, 0.05)
    demand = rng.uniform(*s.demand, (s.n, 1)) * np.array([c.mu for c in cars])[:, None] * G
    ay = demand * _sines(rng, t, s.n, 4, 0.02, 0.15)
    wheelbase = np.array([c.wheelbase for c in cars])[:, None]
    under = np.array([c.understeer_gradient for c in cars])[:, None]
    delta = ay * (wheelbase + under * vx**2) / vx**2  # the linear car's steady steering
    batch = _batch(cars)

    def rates(x: np.ndarray, k: int) -> np.ndarray:
        return np.stack(dynamic.lateral_rates(x[:, 0], x[:, 1], vx[:, k], delta[:, k], batch),
                        axis=-1)

    states = np.empty((s.n, len(t), 2))  # v_y, r of every car at once
    states[:, 0] = np.stack(dynamic.steady_state(vx[:, 0], delta[:, 0], batch), axis=-1)
    h = DT / CAR.substeps
    for k in range(len(t) - 1):  # sequential in time, vectorised over the cars
        x = states[:, k]
        for _ in range(CAR.substeps):  # RK4, the inputs held over the period
            k1 = rates(x, k)
            k2 = rates(x + 0.5 * h * k1, k)
            k3 = rates(x + 0.5 * h * k2, k)
            k4 = rates(x + h * k3, k)
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        states[:, k + 1] = x
    # every row's rates at once: time first, so the cars' (n,) parameters broadcast
    dv_y_now = dynamic.lateral_rates(states[..., 0].T, states[..., 1].T, vx.T, delta.T,
                                     batch)[0].T
    true_ay = dv_y_now + vx * states[..., 1]  # v_y' + vx r at the centre of gravity
    noise = rng.standard_normal((2, s.n, len(t)))
    frames = []
    for i, car in enumerate(cars):
        f = pd.DataFrame({"t": t, "vx": vx[i], "delta": delta[i],
                          "ay_m": true_ay[i] + s.sigma_ay * noise[0, i],
                          "r_m": states[i, :, 1] + s.sigma_r * noise[1, i],
                          "vy": states[i, :, 0], "beta": np.arctan2(states[i, :, 0], vx[i])})
        f.attrs["car"] = dataclasses.asdict(car)
        frames.append(f)
    return frames
