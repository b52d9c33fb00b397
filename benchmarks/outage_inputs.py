"""Dead reckoning through simulated GNSS outages with a speed sensor that reads 2% high and a
steering offset of 10 mrad: the kinematic EKF on the logged inputs, told the true terms, and
with the terms fitted to each blanked log by its fixes (``lbo.observe observer=ekf
adapt=true``'s fit, :mod:`lbo.learn.input_fit`: no truth, no fix inside an outage), on
the log itself (offline: it reads the fixes after each outage), on another drive of the
same car and on the other drives together (what a causal filter can be told). Outages
of 10 s every 25 s and of 30 s every 45 s (:mod:`lbo.scoring.outages`) on ``DRIVES``
single-antenna free drives of 180 s at alpha 1.

Learned filters given as ``label=<run id or checkpoint>`` run beside them in their recursive
form: a window filter with learned input terms (``model.input_terms=true``) or a learned
process-model correction (``model.residual``), trained on simulated drives whose sensors carry
the same errors, learns the terms from its training drives (other drives of the car), not from
the log it filters. What its process model undoes on each log is printed (``implied_inputs``:
its learned terms, or the speed factor and the steering offset its correction applies).

    python benchmarks/outage_inputs.py ["learned filter=<run id>" ...]
"""

import dataclasses
import sys
import time

import pandas as pd
from hydra import compose, initialize_config_dir

from lbo.core.paths import CONF_DIR
from lbo.filters.inputs import InputTerms
from lbo.learn import input_fit
from lbo.logs.io import receiver
from lbo.scoring import outages
from lbo.serve.observer import Observer
from lbo.serve.rows import bicycle_rows
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise
from lbo.sim.truth import Sensors
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate

DRIVES, SPEED_SCALE, OFFSET = 4, 0.02, 0.01
PLAIN, TOLD = "ekf, logged inputs", "ekf, told the true terms"
ADAPTED = "ekf, terms fitted to this log (adapt=true, offline)"
OTHER = "ekf, terms fitted to another drive"
FLEET = "ekf, terms fitted to the other drives together"
with initialize_config_dir(str(CONF_DIR), version_base=None):
    cfg = compose("simulate", ["receiver=single_antenna", "manoeuvre=free_drive", "duration=180",
                               f"sensors.speed_scale={SPEED_SCALE}",
                               f"sensors.steering_offset={OFFSET}"])
vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
vehicle = dataclasses.replace(vehicle, delta_max=0.6)  # the offset reads past 0.5 rad
told = InputTerms.told(Sensors(steering_offset=OFFSET, speed_scale=SPEED_SCALE))
ekf = Observer.load("ekf", vehicle, noise)
nets = {label: Observer.load(source, vehicle, form="recursive")
        for label, source in (a.split("=", 1) for a in sys.argv[1:])}
for label, observer in nets.items():
    print(f"{label}: model.residual={observer.net.net.residual}", flush=True)
tables = {}
for length, every in ((10.0, 25.0), (30.0, 45.0)):
    drives = []
    for seed in range(DRIVES):
        cfg.seed = seed
        log = simulate(cfg)
        spans, blanked = outages.cut(log, outages.Outages(length, every), vehicle.dt)
        m = blanked[["x_m", "y_m", "psi_m"]].to_numpy(dtype=float)
        u = blanked[["V", "delta"]].to_numpy(dtype=float)
        channels = receiver(blanked)
        began = time.perf_counter()
        rows = bicycle_rows(Measurements.of(m, channels), u, vehicle.wheelbase)
        fitted = input_fit.fit(rows, u, vehicle, noise)
        print(f"{length:g} s outages, drive {seed}: {len(spans)} outages; fitted in "
              f"{time.perf_counter() - began:.1f} s ({fitted.runs} EKF runs): "
              f"{fitted.terms.describe()} (the truth: {told.describe()})", flush=True)
        for label, observer in nets.items():
            implied = observer.net.net.implied_inputs(u)  # lbo.models.motion.ProcessModel's
            print(f"{length:g} s outages, drive {seed}: {label}: its process model undoes "
                  f"{implied.describe()}", flush=True)
        drives.append((log, spans, m, u, channels, rows, fitted.terms))
    scored = []
    for seed, (log, spans, m, u, channels, _, own) in enumerate(drives):
        other = drives[(seed + 1) % DRIVES][-1]  # the terms another drive of the car gave
        rest = [d for j, d in enumerate(drives) if j != seed]
        began = time.perf_counter()
        fleet = input_fit.fit([d[5] for d in rest], [d[3] for d in rest], vehicle, noise).terms
        print(f"{length:g} s outages, drive {seed}: the other {len(rest)} drives' terms fitted "
              f"together in {time.perf_counter() - began:.1f} s: {fleet.describe()}", flush=True)
        est = {}
        for name, terms in ((PLAIN, None), (TOLD, told), (ADAPTED, own), (OTHER, other),
                            (FLEET, fleet)):
            ekf.inputs = terms
            e, ok = ekf.run(m, u, receiver=channels)
            est[name] = e.copy()
            est[name][~ok] = float("nan")
        for label, observer in nets.items():
            e, ok = observer.run(m, u, receiver=channels)
            est[label] = e.copy()
            est[label][~ok] = float("nan")
        scored.append(outages.score(est, log, spans, vehicle.dt))
    every_drive = pd.concat(scored)
    table = every_drive.groupby("estimator", sort=False)[["end_m", "drift_pct"]].mean()
    table["outages"] = every_drive.groupby("estimator", sort=False)["outages"].sum()
    table["end_vs_told"] = table["end_m"] / table.loc[TOLD, "end_m"]
    table["end_vs_plain"] = table["end_m"] / table.loc[PLAIN, "end_m"]
    tables[length] = table
    print(f"\n{length:g} s outages every {every:g} s, {DRIVES} drives (mean of the drives' means):")
    print("| estimator | at the end (m) | drift (% of distance) | end vs told | end vs logged |")
    print("|---|---:|---:|---:|---:|")
    for name, r in table.iterrows():
        print(f"| {name} | {r['end_m']:.2f} | {r['drift_pct']:.2f} | {r['end_vs_told']:.2f} | "
              f"{r['end_vs_plain']:.2f} |")
for name in (ADAPTED, OTHER, FLEET, *nets):
    print(f"\nworst '{name}' vs told over the two lengths:",
          f"{max(t.loc[name, 'end_vs_told'] for t in tables.values()):.2f}")
