"""Drives that stop: the training trajectories with standstill, starts from rest, creeping and
cruising (:func:`generate_stop_and_go`), and the stop-and-go drive through town that
``python -m lbo.simulate manoeuvre=stop_and_go`` writes (:func:`drive_stop_and_go`).

The friction-circle set (paper III-A-1) never drops below ``vehicle.v_min``, so an observer
trained on it has never seen a car stand still. These trajectories hold a sequence of speed
targets, each drawn as a stop (V = 0 for several seconds), a creep (0.1-1.5 m/s) or a cruise
(up to ``v_max``), reached at a bounded acceleration; the steering wanders smoothly (also at
standstill, as when parking), limited so the lateral acceleration stays below ``lat_max``.
"""

from __future__ import annotations

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.sim.clothoid import sample
from lbo.sim.manoeuvres import Chain
from lbo.sim.noise import Noise
from lbo.sim.pursuit import drive
from lbo.sim.truth import Car
from lbo.sim.vehicle import Vehicle, f, measure

MODES = ("stop", "creep", "cruise")


def generate_stop_and_go(n_traj: int, n_steps: int, vehicle: Vehicle, noise: Noise,
                         rng: np.random.Generator,
                         p_mode: tuple[float, float, float] = (0.4, 0.2, 0.4),
                         hold: tuple[float, float] = (2.0, 8.0),
                         accel: tuple[float, float] = (0.5, 3.0),
                         steer_rate: float = 0.4, lat_max: float = 4.0,
                         alpha: float = 1.0) -> dict[str, np.ndarray]:
    """Simulate stop-and-go trajectories, all at once (a loop over time only).

    Parameters
    ----------
    n_traj, n_steps : trajectories B and steps T.
    p_mode : probabilities of the next target being a stop, a creep or a cruise.
    hold : (min, max) seconds a target is held once reached (a stop lasts this long).
    accel : (min, max) |acceleration| (m/s^2) towards the target speed.
    steer_rate : largest steering rate (rad/s).
    lat_max : largest lateral acceleration V^2 tan(delta) / L (m/s^2).

    Returns
    -------
    dict with ``z`` (B, T, 3) true states (psi wrapped), ``u`` (B, T, 2) inputs [V, delta],
    ``m`` (B, T, 3) measurements at ``alpha``.
    """
    dt, L = vehicle.dt, vehicle.wheelbase
    z = np.zeros((n_traj, n_steps, 3))
    u = np.zeros((n_traj, n_steps, 2))
    z[:, 0, 2] = rng.uniform(-np.pi, np.pi, n_traj)
    w = rng.standard_normal((n_traj, n_steps, 3)) * np.asarray(noise.process_sigma)
    V = np.where(rng.random(n_traj) < 0.5, 0.0, rng.uniform(0.0, vehicle.v_max, n_traj))
    target = V.copy()
    rate = np.full(n_traj, 1.0)
    left = np.zeros(n_traj, np.int64)  # steps to hold once the target speed is reached
    delta = np.zeros(n_traj)
    delta_target = np.zeros(n_traj)
    tan_max = np.tan(vehicle.delta_max)

    for k in range(n_steps):  # sequential in time, vectorised over the trajectories
        u[:, k, 0], u[:, k, 1] = V, delta
        if k + 1 == n_steps:
            break
        z[:, k + 1] = z[:, k] + f(z[:, k], u[:, k], L) * dt + w[:, k]
        reached = np.abs(V - target) < 1e-9
        left = np.where(reached, left - 1, left)
        new = np.flatnonzero(reached & (left <= 0))
        if new.size:
            mode = rng.choice(3, new.size, p=np.asarray(p_mode) / np.sum(p_mode))
            target[new] = np.select([mode == 0, mode == 1],
                                    [0.0, rng.uniform(0.1, 1.5, new.size)],
                                    rng.uniform(1.5, vehicle.v_max, new.size))
            rate[new] = rng.uniform(*accel, new.size)
            left[new] = np.round(rng.uniform(*hold, new.size) / dt).astype(np.int64)
        redraw = rng.random(n_traj) < dt / 1.5  # a new steering target every 1.5 s on average
        delta_target = np.where(redraw, rng.uniform(-1, 1, n_traj) * vehicle.delta_max,
                                delta_target)
        V = V + np.clip(target - V, -rate * dt, rate * dt)
        tan_lim = np.minimum(tan_max, lat_max * L / np.maximum(V, 1e-6) ** 2)
        limit = np.arctan(tan_lim)
        delta = np.clip(delta + np.clip(delta_target - delta, -steer_rate * dt, steer_rate * dt),
                        -limit, limit)

    z[..., 2] = wrap_angle(z[..., 2])
    m = measure(z, noise.meas(alpha), rng)
    m[..., 2] = wrap_angle(m[..., 2])
    return {"z": z, "u": u, "m": m}


# (kind, value, seconds): "stand" for the seconds, "go" to the speed at |a| = 2 m/s^2 and hold it
STOP_AND_GO_PROFILE = (
    ("stand", 0.0, 5.0), ("go", 10.0, 6.0), ("stand", 0.0, 8.0), ("go", 0.8, 6.0),
    ("stand", 0.0, 4.0), ("go", 13.0, 5.0), ("go", 5.0, 3.0), ("stand", 0.0, 7.0),
    ("go", 2.0, 4.0), ("go", 9.0, 6.0), ("stand", 0.0, 6.0),
)


ACCEL = 2.0  # m/s^2, the stop-and-go drive's acceleration and braking


def stop_and_go_speed(dt: float) -> np.ndarray:
    """(T,) speed profile of the stop-and-go drive, sampled every ``dt``."""
    v, out = 0.0, []
    for kind, target, seconds in STOP_AND_GO_PROFILE:
        if kind == "go":
            n = int(np.ceil(abs(target - v) / (ACCEL * dt)))
            out.append(v + np.sign(target - v) * np.minimum(np.arange(1, n + 1) * ACCEL * dt,
                                                            abs(target - v)))
            v = target
        else:
            n = int(np.ceil(v / (ACCEL * dt)))  # brake to a stop first
            out.append(np.maximum(v - np.arange(1, n + 1) * ACCEL * dt, 0.0))
            v = 0.0
        out.append(np.full(int(round(seconds / dt)), v))
    return np.concatenate(out)


def drive_stop_and_go(vehicle: Vehicle, process_sigma, rng: np.random.Generator,
                      car: Car | None = None) -> dict[str, np.ndarray]:
    """True states z (T, 3), inputs u (T, 2) and the rear slip (T,) (rad) of the stop-and-go
    drive through town, by the kinematic bicycle or by the dynamic ``car``."""
    speed = stop_and_go_speed(vehicle.dt)
    path = Chain().straight(60).turn(10, -90, 4).straight(70).turn(12, 90, 5).straight(60) \
        .turn(9, 90, 4).straight(200).segments
    out = drive([sample(path, 0.1, lead_in=0.0, tail=100.0)], speed[None], vehicle,
                np.asarray(process_sigma), rng, ds=0.1, car=car)
    return {"z": out["z"][0], "u": out["u"][0], "slip": out["slip"][0]}
