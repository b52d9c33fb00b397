"""A truth model kept to lbo's car contract (docs/plugins.md): a single-track car whose tyres
stay linear, where lbo's own (``car=dynamic``) saturate.

The contract, in short: a frozen dataclass whose fields are its ``car.*`` settings, with a
``wheelbase`` (m, the vehicle's) and an ``understeer_gradient`` (rad per m/s^2), and three
methods on the state ``[x, y, psi, v_y, r]`` (the rear axle's pose, the lateral speed of the
centre of gravity, the yaw rate), vectorised over leading dimensions: ``start(z0, u0)``,
``step(s, u, dt)`` and ``rear_slip(s, u)``. lbo does the rest: the simulator, the data sets,
a receiver's velocity, and the EKF told the car.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

SUBSTEPS = 4
"""RK4 sub-steps per sampling period."""
SLOW = 2.0
"""m/s: the slip angles are taken at no less than this speed (they divide by it)."""


@dataclass(frozen=True)
class LinearCar:
    """A single-track car with linear tyres: each axle's force is its cornering stiffness
    times its slip angle, however large."""

    mass: float = 1500.0
    yaw_inertia: float = 2250.0
    l_f: float = 1.2
    l_r: float = 1.5
    c_f: float = 80_000.0
    c_r: float = 100_000.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"car.{f.name} must be a number > 0, got {value!r}")

    @property
    def wheelbase(self) -> float:
        return self.l_f + self.l_r

    @property
    def understeer_gradient(self) -> float:
        return self.mass / self.wheelbase * (self.l_r / self.c_f - self.l_f / self.c_r)

    def _rates(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        psi, v_y, r = s[..., 2], s[..., 3], s[..., 4]
        v, delta = u[..., 0], u[..., 1]
        fast = np.maximum(v, SLOW)
        f_f = self.c_f * (delta - (v_y + self.l_f * r) / fast)
        f_r = self.c_r * (-(v_y - self.l_r * r) / fast)
        side = v_y - self.l_r * r  # the rear axle's lateral speed
        return np.stack([v * np.cos(psi) - side * np.sin(psi),
                         v * np.sin(psi) + side * np.cos(psi),
                         r,
                         (f_f * np.cos(delta) + f_r) / self.mass - v * r,
                         (self.l_f * f_f * np.cos(delta) - self.l_r * f_r) / self.yaw_inertia],
                        axis=-1)

    def start(self, z0: np.ndarray, u0: np.ndarray) -> np.ndarray:
        """(..., 5): the poses z0, turning at the kinematic bicycle's rate for u0, no side
        speed of the rear axle (v_y = l_r r)."""
        r = u0[..., 0] * np.tan(u0[..., 1]) / self.wheelbase
        return np.concatenate([z0, (self.l_r * r)[..., None], r[..., None]], axis=-1)

    def step(self, s: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        h = dt / SUBSTEPS
        for _ in range(SUBSTEPS):
            k1 = self._rates(s, u)
            k2 = self._rates(s + 0.5 * h * k1, u)
            k3 = self._rates(s + 0.5 * h * k2, u)
            k4 = self._rates(s + h * k3, u)
            s = s + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return s

    def rear_slip(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.arctan2(s[..., 3] - self.l_r * s[..., 4], np.maximum(u[..., 0], 1e-9))
