"""Kinematic bicycle model (paper eqs. 1-3), vectorised over any leading batch dimensions.

State ``z = [x, y, psi]`` (m, m, rad) at the rear axle, input ``u = [V, delta]`` (m/s, rad).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lbo.core.angles import wrap_angle  # noqa: F401 (user code imports it from here too)
from lbo.core.errors import LboError


@dataclass(frozen=True, kw_only=True)
class Vehicle:
    """Vehicle parameters and the input limits used by the data generators.

    Attributes
    ----------
    dt : float
        Sampling period (s); the paper uses 0.02 s.
    wheelbase : float
        L (m); the paper gives none, 2.7 m is a passenger car.
    v_min, v_max : float
        Speed range (m/s) the generators keep to.
    delta_max : float
        Steering limit |delta| <= delta_max (rad).
    """

    dt: float = 0.02
    wheelbase: float = 2.7
    v_min: float = 1.0
    v_max: float = 25.0
    delta_max: float = 0.5

    def __post_init__(self) -> None:
        checks = {
            "vehicle.dt": (self.dt > 0, "a period in seconds > 0"),
            "vehicle.wheelbase": (self.wheelbase > 0, "a length in metres > 0"),
            "vehicle.v_min": (self.v_min > 0, "a speed in m/s > 0"),
            "vehicle.v_max": (self.v_max > self.v_min, "a speed in m/s > vehicle.v_min"),
            "vehicle.delta_max": (0 < self.delta_max < np.pi / 2, "an angle in rad in (0, pi/2)"),
        }
        for field, (ok, form) in checks.items():
            if not ok:
                raise LboError(f"{field} must be {form}, got {getattr(self, field.split('.')[1])}")

    @classmethod
    def from_cfg(cls, cfg) -> Vehicle:
        """Build from a mapping with the fields above (e.g. the Hydra group ``vehicle``)."""
        return cls(**{k: float(cfg[k]) for k in ("dt", "wheelbase", "v_min", "v_max", "delta_max")})


def f(z: np.ndarray, u: np.ndarray, wheelbase: float) -> np.ndarray:
    """Continuous dynamics ``dz/dt`` (eq. 1). z: (..., 3), u: (..., 2) -> (..., 3)."""
    psi = z[..., 2]
    v, delta = u[..., 0], u[..., 1]
    return np.stack([v * np.cos(psi), v * np.sin(psi), v * np.tan(delta) / wheelbase], axis=-1)


def step(z: np.ndarray, u: np.ndarray, dt: float, wheelbase: float,
         w: np.ndarray | None = None) -> np.ndarray:
    """Discrete step (eq. 2): ``z + f(z, u) dt + w``. z: (..., 3), u: (..., 2), w: (..., 3)."""
    z_next = z + f(z, u, wheelbase) * dt
    return z_next if w is None else z_next + w


def jacobian(z: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """d step / d z. z: (..., 3), u: (..., 2) -> (..., 3, 3)."""
    psi, v = z[..., 2], u[..., 0]
    jac = np.zeros(z.shape[:-1] + (3, 3))
    jac[..., 0, 0] = jac[..., 1, 1] = jac[..., 2, 2] = 1.0
    jac[..., 0, 2] = -v * np.sin(psi) * dt
    jac[..., 1, 2] = v * np.cos(psi) * dt
    return jac


def simulate(z0: np.ndarray, u: np.ndarray, dt: float, wheelbase: float,
             process_sigma: np.ndarray | Sequence[float] | None = None,
             rng: np.random.Generator | None = None) -> np.ndarray:
    """Roll the discrete model forward over known inputs.

    Parameters
    ----------
    z0 : (B, 3) initial states.
    u : (B, T, 2) inputs; ``u[:, k]`` moves ``z_k`` to ``z_{k+1}``.
    process_sigma : (3,) standard deviations of w_k, or None for a noise-free run.

    Returns
    -------
    (B, T, 3) states z_0 .. z_{T-1}; psi is left unwrapped (continuous).
    """
    b, t = u.shape[:2]
    z = np.empty((b, t, 3))
    z[:, 0] = z0
    if process_sigma is not None:
        assert rng is not None, "process_sigma needs an rng"
        w = rng.standard_normal((b, t - 1, 3)) * np.asarray(process_sigma)
    for k in range(t - 1):  # sequential in time, vectorised over the batch
        z[:, k + 1] = step(z[:, k], u[:, k], dt, wheelbase,
                           None if process_sigma is None else w[:, k])
    return z


def measure(z: np.ndarray, sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Measurements ``m = z + v`` (eq. 3), v ~ N(0, diag(sigma^2)). z: (..., 3) -> (..., 3)."""
    return z + rng.standard_normal(z.shape) * np.asarray(sigma)
