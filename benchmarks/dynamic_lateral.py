"""Side slip on the simulated car that slips: what the EKF told the true car (the dynamic oracle,
:func:`lbo.filters.dynamic_ekf.dynamic_ekf_lateral`) estimates of beta, v_y and r from the
pose fixes alone, at alpha 1, 3 and 6, beside the kinematic bicycle's side slip and the same
filter told 3x softer tyres.

The drives: 16 slaloms of 20 s at 10-12 m/s (steering 0.06 sin(2 pi 0.3 t)), the default
single-track car (:class:`lbo.sim.dynamic.SingleTrack`), the paper's process noise on the pose
and its measurement noise times alpha. beta is the centre of gravity's side slip,
atan2(v_y, V). NEES: the mean of beta's error squared over its variance (1 is honest).

    python benchmarks/dynamic_lateral.py
"""

from dataclasses import replace

import numpy as np

from lbo.filters.dynamic_ekf import dynamic_ekf_lateral
from lbo.filters.lateral import kinematic_beta
from lbo.sim import dynamic
from lbo.sim.dynamic import SingleTrack
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

VEHICLE, CAR, NOISE = Vehicle(), SingleTrack(), Noise.preset("paper")
G, T = 16, 1000
rng = np.random.default_rng(0)
t = np.arange(T) * VEHICLE.dt
u = np.stack([np.broadcast_to(rng.uniform(10, 12, (G, 1)), (G, T)),
              0.06 * np.sin(2 * np.pi * 0.3 * t + rng.uniform(0, 2 * np.pi, (G, 1)))], -1)
z0 = np.column_stack([rng.normal(0, 50, G), rng.normal(0, 50, G), rng.uniform(-np.pi, np.pi, G)])
s = dynamic.simulate(z0, u, VEHICLE.dt, CAR, np.array(NOISE.process_sigma), rng)
truth = np.arctan2(s[..., 3], u[..., 0])


def deg(err: np.ndarray) -> float:
    return float(np.rad2deg(np.sqrt(np.mean(err**2))))


print(f"beta over the drives: RMS {deg(truth):.3f} deg, at most "
      f"{np.rad2deg(np.abs(truth).max()):.2f} deg\n")
print("| alpha | EKF told the car: beta RMSE (deg) | its beta NEES | v_y RMSE (m/s) | "
      "r RMSE (rad/s) | told 3x softer tyres (deg) | kinematic bicycle (deg) |")
print("|---|---:|---:|---:|---:|---:|---:|")
soft = replace(CAR, c_f=CAR.c_f / 3, c_r=CAR.c_r / 3)
for alpha in (1.0, 3.0, 6.0):
    m = s[..., :3] + rng.standard_normal((G, T, 3)) * np.array(NOISE.measurement_sigma) * alpha
    _, lat = dynamic_ekf_lateral(m, u, VEHICLE, CAR, NOISE.Q, NOISE.R(alpha))
    _, wrong = dynamic_ekf_lateral(m, u, VEHICLE, soft, NOISE.Q, NOISE.R(alpha))
    err = lat.beta(u[..., 0]) - truth
    e = lat.mean - s[..., 3:5]
    print(f"| {alpha:g} | {deg(err):.4f} | {np.mean(err**2 / lat.beta_var(u[..., 0])):.4f} | "
          f"{np.sqrt(np.mean(e[..., 0] ** 2)):.5f} | {np.sqrt(np.mean(e[..., 1] ** 2)):.5f} | "
          f"{deg(wrong.beta(u[..., 0]) - truth):.3f} | "
          f"{deg(kinematic_beta(u[..., 1], CAR) - truth):.3f} |")
