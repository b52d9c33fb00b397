"""Side slip on the simulated car that slips: what the EKF told the true car (``oracle_dynamic``,
:func:`lbo.filters.classical.oracle_dynamic_lateral`) estimates of beta, v_y and r from the
pose fixes alone, on ``data=dynamic``'s test manoeuvres at alpha 1, 3 and 6, beside the
kinematic bicycle's side slip and the same filter told tyres 3x softer than the car's.

Only the test set is made (in memory, from the config; nothing is written). Its rows hold the
car's true v_y and r (:data:`lbo.sim.columns.LATERAL`); the scored rows (after the run-in)
are scored. beta is the centre of gravity's side slip, atan2(v_y, V). NEES: the mean of
beta's error squared over the filter's variance of it (1 is honest).

    python benchmarks/dynamic_lateral.py [data=dynamic ...]
"""

import dataclasses
import sys

import numpy as np
from hydra import compose, initialize_config_dir

from lbo.core.paths import CONF_DIR
from lbo.filters.classical import oracle_dynamic_lateral
from lbo.filters.lateral import kinematic_beta
from lbo.sim import schema
from lbo.sim.datasets import make_test, spec_from_cfg

with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
    cfg = compose("datagen", ["data=dynamic", *sys.argv[1:]])
spec = spec_from_cfg(cfg)
car, vehicle = spec.truth.car, spec.vehicle
assert car is not None, "the data set must be drawn from a car that slips (car=dynamic)"
test = schema.to_arrays(make_test(spec))
soft = dataclasses.replace(spec.truth, car=dataclasses.replace(car, c_f=car.c_f / 3,
                                                                 c_r=car.c_r / 3))


def deg(err: np.ndarray) -> float:
    return float(np.rad2deg(np.sqrt(np.mean(err**2))))


print(f"data={spec.name}: {len(set(test.traj))} manoeuvres, alphas "
      f"{sorted(set(test.alpha.tolist()))}")
print("\n| alpha | told the car: beta RMSE (deg) | its beta NEES | v_y RMSE (m/s) | "
      "r RMSE (rad/s) | told 3x softer tyres (deg) | kinematic bicycle (deg) | beta RMS (deg) |")
print("|---|---:|---:|---:|---:|---:|---:|---:|")
for alpha in (1.0, 3.0, 6.0):
    t = test.take(test.alpha == alpha)
    assert t.lateral is not None
    vx = t.u[..., 0] / (1.0 + spec.truth.sensors.speed_scale)  # the true speed, not the logged
    truth = np.arctan2(t.lateral[..., 0], vx)
    _, lat = oracle_dynamic_lateral(t.m, t.u, vehicle, spec.noise, t.alpha, spec.truth)
    _, wrong = oracle_dynamic_lateral(t.m, t.u, vehicle, spec.noise, t.alpha, soft)
    s = t.mask
    err = (lat.beta(vx) - truth)[s]
    e = (lat.mean - t.lateral)[s]
    delta = t.u[..., 1] - spec.truth.sensors.steering_offset
    print(f"| {alpha:g} | {deg(err):.2e} | {np.mean(err**2 / lat.beta_var(vx)[s]):.2e} | "
          f"{np.sqrt(np.mean(e[:, 0] ** 2)):.2e} | {np.sqrt(np.mean(e[:, 1] ** 2)):.2e} | "
          f"{deg((wrong.beta(vx) - truth)[s]):.3f} | "
          f"{deg((kinematic_beta(delta, car) - truth)[s]):.3f} | {deg(truth[s]):.3f} |")
