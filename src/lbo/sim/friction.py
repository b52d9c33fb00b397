"""Training set: trajectories whose accelerations fill the friction circle evenly (paper III-A-1).

A 2-D density grid over (longitudinal, lateral) acceleration inside a circle of radius
``radius`` is shared by all trajectories. Whenever a trajectory's current target expires it
draws a few candidate cells, drops those its speed cannot reach, and takes the least-filled
one. The paper's two equations are then solved for the next V and delta. They are written in
the world frame; rotated by -psi they read, in the vehicle frame,

    a_lon,k = (V_{k+1} - V_k) / dt,        a_lat,k = V_{k+1} tan(delta_{k+1}) V_k / L,

which is what the grid (and the paper's Fig. 2) is drawn in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle, f, measure

G = 9.81  # m/s^2


@dataclass(frozen=True)
class Grid:
    """Square grid of ``n x n`` cells over [-radius, radius]^2; only cells whose centre lies
    inside the circle are targets and count towards coverage."""

    radius: float
    n: int

    @property
    def edges(self) -> np.ndarray:
        return np.linspace(-self.radius, self.radius, self.n + 1)

    @property
    def centres(self) -> np.ndarray:
        """(n*n, 2) cell centres as (a_lon, a_lat), row-major in a_lon."""
        c = 0.5 * (self.edges[1:] + self.edges[:-1])
        lon, lat = np.meshgrid(c, c, indexing="ij")
        return np.stack([lon.ravel(), lat.ravel()], axis=-1)

    @property
    def inside(self) -> np.ndarray:
        """(n*n,) bool, cells whose centre is inside the circle."""
        return np.hypot(*self.centres.T) <= self.radius

    def cell(self, a: np.ndarray) -> np.ndarray:
        """Flat cell index of accelerations a (..., 2); -1 outside the square."""
        i = np.floor((a + self.radius) / (2 * self.radius) * self.n).astype(np.int64)
        ok = np.all((i >= 0) & (i < self.n), axis=-1)
        return np.where(ok, i[..., 0] * self.n + i[..., 1], -1)

    def counts(self, a: np.ndarray) -> np.ndarray:
        """(n*n,) number of samples of a (..., 2) per cell."""
        idx = self.cell(a).ravel()
        return np.bincount(idx[idx >= 0], minlength=self.n * self.n)

    def coverage(self, a: np.ndarray) -> float:
        """Share of the cells inside the circle that hold at least one sample."""
        return float(np.mean(self.counts(a)[self.inside] > 0))


def accelerations(V: np.ndarray, delta: np.ndarray, dt: float, wheelbase: float,
                  understeer: float = 0.0) -> np.ndarray:
    """Vehicle-frame accelerations of an input sequence. V, delta: (..., T) -> (..., T-1, 2).

    ``understeer``: K of a car that slips (the steady-state lateral acceleration of
    :func:`generate_train`); 0 for the kinematic bicycle."""
    a_lon = np.diff(V, axis=-1) / dt
    a_lat = V[..., 1:] * np.tan(delta[..., 1:]) * V[..., :-1] / (
        wheelbase + understeer * V[..., 1:] * V[..., :-1])
    return np.stack([a_lon, a_lat], axis=-1)


def generate_train(n_traj: int, n_steps: int, vehicle: Vehicle, noise: Noise,
                   rng: np.random.Generator, radius: float = 0.5 * G, grid: int = 20,
                   hold: tuple[float, float] = (0.5, 3.0), jerk: float = 8.0,
                   candidates: int = 8, alpha: float = 1.0,
                   understeer: float = 0.0) -> dict[str, np.ndarray]:
    """Simulate the friction-circle training trajectories, all at once.

    Parameters
    ----------
    n_traj, n_steps : number of trajectories B and steps T per trajectory.
    radius : friction-circle radius (m/s^2).
    grid : cells per axis of the density grid.
    hold : (min, max) seconds a target acceleration is held before a new one is drawn.
    jerk : rate limit (m/s^3) on the commanded acceleration, so inputs stay smooth.
    candidates : cells drawn per choice; the least-filled reachable one wins.
    understeer : the car's understeer gradient K (rad per m/s^2; 0 for the kinematic bicycle):
        the steering is chosen from the steady-state ``a_lat = V^2 tan(delta) / (L + K V^2)``,
        so that a car that understeers still fills the circle.

    Returns
    -------
    dict with ``z`` (B, T, 3) true states (psi wrapped), ``u`` (B, T, 2) inputs [V, delta],
    ``m`` (B, T, 3) measurements at ``alpha``.
    """
    dt, L = vehicle.dt, vehicle.wheelbase
    g = Grid(radius, grid)
    centres, inside = g.centres, np.flatnonzero(g.inside)
    cell_size = 2 * radius / grid
    counts = np.zeros(grid * grid, np.int64)
    tan_max = np.tan(vehicle.delta_max)

    z = np.zeros((n_traj, n_steps, 3))
    u = np.zeros((n_traj, n_steps, 2))
    z[:, 0, 2] = rng.uniform(-np.pi, np.pi, n_traj)
    V = rng.uniform(vehicle.v_min, vehicle.v_max, n_traj)
    delta = np.zeros(n_traj)
    a_cmd = np.zeros((n_traj, 2))
    target = np.zeros((n_traj, 2))
    left = np.zeros(n_traj, np.int64)  # steps left on the current target
    w = rng.standard_normal((n_traj, n_steps, 3)) * np.asarray(noise.process_sigma)

    for k in range(n_steps):  # sequential in time, vectorised over the trajectories
        u[:, k, 0], u[:, k, 1] = V, delta
        if k + 1 == n_steps:
            break
        z[:, k + 1] = z[:, k] + f(z[:, k], u[:, k], L) * dt + w[:, k]

        new = np.flatnonzero(left <= 0)
        if new.size:
            cand = inside[rng.integers(0, inside.size, (new.size, candidates))]
            a_c = centres[cand] + rng.uniform(-0.5, 0.5, cand.shape + (2,)) * cell_size
            horizon = np.minimum(hold[1], 2.0)
            v_end = V[new, None] + a_c[..., 0] * horizon
            # how far a candidate is out of reach (m/s of speed, m/s^2 of lateral acceleration);
            # unreachable ones lose to any reachable one, and among them the nearest wins
            reach = 0.95 * V[new, None] ** 2 * tan_max / (L + understeer * V[new, None] ** 2)
            miss = (np.maximum(v_end - vehicle.v_max, 0) + np.maximum(vehicle.v_min - v_end, 0)
                    + np.maximum(np.abs(a_c[..., 1]) - reach, 0))
            score = counts[cand] + (miss > 0) * (counts.sum() + 1) * (1 + miss)
            pick = np.argmin(score, axis=1)
            target[new] = a_c[np.arange(new.size), pick]
            left[new] = np.round(rng.uniform(*hold, new.size) / dt).astype(np.int64)
        left -= 1

        a_cmd += np.clip(target - a_cmd, -jerk * dt, jerk * dt)
        V_next = np.clip(V + a_cmd[:, 0] * dt, vehicle.v_min, vehicle.v_max)
        turn = L + understeer * (V_next * V)  # L for the kinematic bicycle
        tan_d = np.clip(a_cmd[:, 1] * turn / (V_next * V), -tan_max, tan_max)
        delta_next = np.arctan(tan_d)
        realised = np.stack([(V_next - V) / dt, V_next * tan_d * V / turn], axis=-1)
        counts += g.counts(realised)
        V, delta = V_next, delta_next

    z[..., 2] = wrap_angle(z[..., 2])
    m = measure(z, noise.meas(alpha), rng)
    m[..., 2] = wrap_angle(m[..., 2])
    return {"z": z, "u": u, "m": m}
