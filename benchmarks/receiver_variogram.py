"""The hill drive's receiver as its variogram reads it, without truth and against the truth,
drive by drive; then leave-one-drive-out of the gyro EKF with its receiver's factors set by
the variogram of the other drives and nothing else learned (``learn.receiver_noise=variogram``
without the innovations' fit of the rest: what the variogram alone buys).

    python benchmarks/receiver_variogram.py      # about 1 min on a 2-core CPU
"""

import dataclasses

import numpy as np
from omegaconf import OmegaConf

from lbo.learn.gyro_fit import Settings
from lbo.learn.variogram import SILL_S, course_errors, fix_errors
from lbo.logs import hguide
from lbo.scoring import drives as across
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

vehicle = Vehicle()
noise = Noise.from_cfg(OmegaConf.load("conf/noise/paper.yaml"))  # lbo.realdrive's default
drives = hguide.drives(hguide.to_log(hguide.read(), vehicle))
start = Settings.from_cfg(OmegaConf.load("conf/realdrive.yaml").learn).start(noise.Q)

print("| drive | fixes: one fix (m) | over 10-30 s (m) | the truth's: one fix | over 10-30 s "
      "| rho | accuracy_scale | course: one fix (mrad) | over 5-20 s | rho | widening |")
print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
for k, d in enumerate(drives):
    fixes, course = fix_errors(d), course_errors(d)
    # the same variogram of the fixes' error against the truth, to check what it reads
    rows = np.isfinite(d["x_m"].to_numpy(float))
    err = d.loc[rows, ["x_m", "y_m"]].to_numpy(float) - d.loc[rows, ["x", "y"]].to_numpy(float)
    changes = {lag: (err[lag:] - err[:-lag]) for lag in (1, *(round(s) for s in SILL_S))}
    truth_step = float(np.mean(changes[1]**2) / 2)
    truth_sill = float(np.mean(np.concatenate([changes[round(s)] for s in SILL_S])**2) / 2)
    print(f"| {k + 1} | {np.sqrt(fixes.step):.3f} | {np.sqrt(fixes.sill):.3f} | "
          f"{np.sqrt(truth_step):.3f} | {np.sqrt(truth_sill):.3f} | {fixes.rho:.2f} | "
          f"{fixes.accuracy_scale:.2f} | {1e3 * np.sqrt(course.step):.1f} | "
          f"{1e3 * np.sqrt(course.sill):.1f} | {course.rho:.2f} | {course.widening:.2f} |")


def learn(k: int, train: list) -> across.Fold:
    fixes, course = fix_errors(train), course_errors(train)
    accuracy = dataclasses.replace(start, accuracy_scale=fixes.accuracy_scale)
    both = dataclasses.replace(accuracy, velocity_scale=course.widening)
    return across.Fold({"gyro, accuracy by the fixes' variogram, the rest the defaults": accuracy,
                        "gyro, accuracy and velocity by the variogram, the rest the defaults":
                        both}, {})


table = across.leave_one_out(drives, learn, ["ekf", "gyro"], vehicle, noise, progress=None)
print()
print(across.markdown(across.summary(table)), end="")
