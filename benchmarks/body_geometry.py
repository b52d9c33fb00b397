"""How much of a learned single-track body's side-slip error is where it put the centre of
gravity. Position fixes see the rear axle, whose lateral speed is ``v_y - l_r r``; the body
learns ``l_r`` with its tyres, and beta at the centre of gravity reads it. The body's carried
``[v_y, r]`` on a test set of a car that slips, at one noise level, is scored as carried, and
with ``v_y`` moved to the true centre of gravity (``v_y + (l_r true - l_r learned) r``: the
rear axle's lateral speed and the yaw rate kept), as a user who knows the car's geometry from
its data sheet would read it; the rear axle's lateral speed and the yaw rate beside them.

    python benchmarks/body_geometry.py <checkpoint> <data set folder> [alpha, default 1]
"""

import sys
from pathlib import Path

import numpy as np

from lbo.scoring.grid import load_test
from lbo.scoring.lateral import carried, rmse, truth_of
from lbo.sim.truth import of_folder
from lbo.sim.vehicle import Vehicle
from lbo.tracking.artifacts import load_net

ckpt, folder = sys.argv[1], Path(sys.argv[2])
alpha = float(sys.argv[3]) if len(sys.argv) > 3 else 1.0
truth = of_folder(folder, Vehicle().wheelbase)
car = truth.car
if car is None or not hasattr(car, "l_r"):
    sys.exit(f"{folder}: not a set drawn from a single-track car")
arr = load_test(folder / "test.parquet")
arr = arr.take(np.isclose(arr.alpha, alpha))
net = load_net(ckpt)[0]
body = carried(net, arr)  # (G, T, 2) [v_y, r]
learned = net.net.body_parameters()["l_r"]
true = truth_of(arr, truth)  # beta, vy, r (G, T)
vx, pick = arr.u[..., 0], arr.mask
moved = body[..., 0] + (car.l_r - learned) * body[..., 1]
print(f"alpha {alpha:g}: the body's l_r {learned:.3f} m, the car's {car.l_r:.3f} m")
print(f"beta RMSE as carried: "
      f"{np.degrees(rmse(np.arctan2(body[..., 0], vx), true['beta'], pick)):.3f} deg")
print(f"beta RMSE at the car's centre of gravity: "
      f"{np.degrees(rmse(np.arctan2(moved, vx), true['beta'], pick)):.3f} deg")
rear_true = true["vy"] - car.l_r * true["r"]
print(f"the rear axle's lateral speed: RMSE "
      f"{rmse(body[..., 0] - learned * body[..., 1], rear_true, pick):.4f} m/s (its own RMS "
      f"{rmse(rear_true, np.zeros_like(rear_true), pick):.4f} m/s); "
      f"r: RMSE {rmse(body[..., 1], true['r'], pick):.2e} rad/s")
