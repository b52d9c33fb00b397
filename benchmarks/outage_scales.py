"""Dead reckoning through simulated GNSS outages with a speed sensor that reads 2% high: the
gyro EKF with its defaults, told the true factor, and adapted to each blanked log by its
innovations with factors on the speed and the gyro (``lbo.observe adapt=true
adapt_scales=true``'s fit: no truth, no fix inside an outage); the kinematic EKF beside them.
Outages of 10 s every 25 s and of 30 s every 45 s (:mod:`lbo.scoring.outages`) on ``DRIVES``
single-antenna free drives of 180 s at alpha 1.

    python benchmarks/outage_scales.py
"""

import time

import pandas as pd
from hydra import compose, initialize_config_dir

from lbo.core.paths import CONF_DIR
from lbo.filters.gyro_noise import GyroNoise
from lbo.learn import gyro_fit
from lbo.scoring import outages
from lbo.scoring.receiver import EKF, score
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate

DRIVES, SCALE = 4, 1.02
ADAPTED = "gyro, adapted with factors (adapt_scales=true)"
with initialize_config_dir(str(CONF_DIR), version_base=None):
    cfg = compose("simulate", ["receiver=single_antenna", "manoeuvre=free_drive",
                               "duration=180", f"receiver.speed_scale={SCALE}"])
vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
defaults = GyroNoise.from_q(noise.Q)
tables = {}
for length, every in ((10.0, 25.0), (30.0, 45.0)):
    rows = []
    for seed in range(DRIVES):
        cfg.seed = seed
        log = simulate(cfg)
        spans, blanked = outages.cut(log, outages.Outages(length, every), vehicle.dt)
        began = time.perf_counter()
        fitted = gyro_fit.adapt(blanked, defaults.with_scales(), vehicle, noise)
        print(f"{length:g} s outages, drive {seed}: {len(spans)} outages; adapted in "
              f"{time.perf_counter() - began:.0f} s: speed x{fitted.noise.speed_scale:.4f}, "
              f"gyro x{fitted.noise.gyro_scale:.4f} (the truth: speed x{1 / SCALE:.4f})",
              flush=True)
        learned = {"gyro, told the speed's factor": defaults.with_scales(1 / SCALE, 1.0),
                   ADAPTED: fitted.noise}
        _, est = score(blanked, ["ekf", "gyro"], vehicle, noise, learned)
        rows.append(outages.score(est, log, spans, vehicle.dt))
    every_drive = pd.concat(rows)
    table = every_drive.groupby("estimator", sort=False)[["end_m", "drift_pct"]].mean()
    table["outages"] = every_drive.groupby("estimator", sort=False)["outages"].sum()
    table["end_vs_told"] = table["end_m"] / table.loc["gyro, told the speed's factor", "end_m"]
    table["end_vs_ekf"] = table["end_m"] / table.loc[EKF, "end_m"]
    tables[length] = table
    print(f"\n{length:g} s outages every {every:g} s, {DRIVES} drives (mean of the drives' means):")
    print("| estimator | at the end (m) | drift (% of distance) | end vs told | end vs ekf |")
    print("|---|---:|---:|---:|---:|")
    for name, r in table.iterrows():
        print(f"| {name} | {r['end_m']:.2f} | {r['drift_pct']:.2f} | {r['end_vs_told']:.2f} | "
              f"{r['end_vs_ekf']:.2f} |")
print("\nworst 'adapted vs told' over the two lengths:",
      f"{max(t.loc[ADAPTED, 'end_vs_told'] for t in tables.values()):.2f}")
