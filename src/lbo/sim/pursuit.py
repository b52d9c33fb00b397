"""Pure-pursuit driving of sampled paths, vectorised over a batch of paths."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.sim.dynamic import lateral_noise
from lbo.sim.truth import Car
from lbo.sim.vehicle import Vehicle, f


def smooth_noise(n_traj: int, n_steps: int, dt: float, rng: np.random.Generator,
                 n_waves: int = 3, freq: tuple[float, float] = (0.03, 0.25)) -> np.ndarray:
    """Smooth zero-mean random signals in [-1, 1]: sums of sinusoids. -> (B, T)."""
    t = np.arange(n_steps) * dt
    fr = rng.uniform(*freq, (n_traj, n_waves, 1))
    ph = rng.uniform(0, 2 * np.pi, (n_traj, n_waves, 1))
    return np.sin(2 * np.pi * fr * t + ph).sum(axis=1) / n_waves


def drive(paths: list[np.ndarray], speed: np.ndarray, vehicle: Vehicle,
          process_sigma: np.ndarray, rng: np.random.Generator, ds: float = 0.1,
          gain: float = 0.4, lookahead: tuple[float, float] = (3.0, 15.0),
          car: Car | None = None, lateral_sigma: Sequence[float] | None = None
          ) -> dict[str, np.ndarray]:
    """Drive every path with a pure-pursuit controller at the given speed profile.

    Parameters
    ----------
    paths : G arrays (P_g, 4) of ``[s, x, y, theta]`` sampled every ``ds`` m (see clothoid.sample);
        the vehicle starts at each path's first sample, on its heading.
    speed : (G, T) speed V_k (m/s) to hold at every step.
    gain : look-ahead distance = clip(gain * V, *lookahead) metres.
    car : None drives the kinematic bicycle; else this car that slips (:class:`Car`: the
        single-track of :mod:`lbo.sim.dynamic`, or a registered one), which the controller
        steers all the same.
    lateral_sigma : (2,) standard deviations of the disturbances added to the car's v_y and r
        after each step (:func:`lbo.sim.dynamic.lateral_noise`), drawn after the process
        noise; None or zeros: none.

    Returns
    -------
    dict with ``z`` (G, T, 3) true states (psi wrapped), ``u`` (G, T, 2) inputs [V, delta],
    ``slip`` (G, T) the rear axle's side slip (rad, ``car.rear_slip``; 0 for
    the kinematic bicycle), which a receiver's velocity shows, and ``lateral`` (G, T, 2) the
    car's ``[v_y, r]`` (0 for the kinematic bicycle).
    """
    g, n_steps = speed.shape
    p_max = max(len(p) for p in paths)
    # pad every path to one length by repeating its end; tails are long enough never to be reached
    pts = np.stack([np.pad(p[:, 1:3], ((0, p_max - len(p)), (0, 0)), mode="edge") for p in paths])
    z = np.zeros((g, n_steps, 3))
    z[:, 0] = [(p[0, 1], p[0, 2], p[0, 3]) for p in paths]
    u = np.zeros((g, n_steps, 2))
    w = rng.standard_normal((g, n_steps, 3)) * np.asarray(process_sigma)
    gusts = lateral_noise(rng, (g, n_steps), lateral_sigma)
    rows = np.arange(g)
    window = int(np.ceil(2.0 * vehicle.v_max * vehicle.dt / ds)) + 20
    idx = np.zeros(g, np.int64)
    offsets = np.arange(window)
    tan_max = np.tan(vehicle.delta_max)
    lateral = np.zeros((g, 2))  # the dynamic car's v_y and r; it starts straight
    lateral_k = np.zeros((g, n_steps, 2))

    for k in range(n_steps):  # sequential in time (feedback), vectorised over paths
        cand = np.minimum(idx[:, None] + offsets, p_max - 1)
        d2 = np.sum((pts[rows[:, None], cand] - z[:, k, None, :2]) ** 2, axis=-1)
        idx = cand[rows, np.argmin(d2, axis=1)]
        v = speed[:, k]
        ahead = np.clip(gain * v, *lookahead)
        target = pts[rows, np.minimum(idx + np.round(ahead / ds).astype(np.int64), p_max - 1)]
        rel = target - z[:, k, :2]
        alpha = np.arctan2(rel[:, 1], rel[:, 0]) - z[:, k, 2]
        dist = np.maximum(np.hypot(rel[:, 0], rel[:, 1]), 1e-3)
        tan_d = np.clip(2 * vehicle.wheelbase * np.sin(alpha) / dist, -tan_max, tan_max)
        u[:, k, 0], u[:, k, 1] = v, np.arctan(tan_d)
        if k + 1 == n_steps:
            break
        if car is None:
            z[:, k + 1] = z[:, k] + f(z[:, k], u[:, k], vehicle.wheelbase) * vehicle.dt + w[:, k]
        else:
            s = car.step(np.concatenate([z[:, k], lateral], axis=-1), u[:, k], vehicle.dt)
            z[:, k + 1], lateral = s[:, :3] + w[:, k], s[:, 3:] + gusts[:, k]
            lateral_k[:, k + 1] = lateral
    slip = (np.zeros((g, n_steps)) if car is None
            else car.rear_slip(np.concatenate([z, lateral_k], axis=-1), u))
    z[..., 2] = wrap_angle(z[..., 2])
    return {"z": z, "u": u, "slip": slip, "lateral": lateral_k}
