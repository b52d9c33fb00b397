"""`python -m lbo.realdrive`: a real car drive end to end, every classical observer on it.

    python -m lbo.realdrive [output_dir=reports/realdrive] [observers=[ekf,adaptive,ukf]]

Reads the onavdata hill drive (``pip install 'lbo[real]'``; :mod:`lbo.sim.hguide`), fits the
antenna's lever arm and the fixes' latency, and writes it as three lbo logs, one per time span:
``hill_train.parquet`` (the first 60%), ``hill_val.parquet`` and ``hill_test.parquet`` (20%
each). Each takes ``python -m lbo.observe`` as it is. On the test span it scores, against the
INS/GNSS truth at the antenna:

- the raw fixes (position at the fix rows; heading: the course over ground of the receiver's
  velocity, where the car moves fast enough for it to be one);
- each classical observer with the receiver's channels (its reported accuracy as R, its
  velocity as the course), and the EKF without them (lbo's R, no velocity) and smoothed (RTS,
  offline), as :meth:`lbo.Observer.run` gives them.

It writes ``results.csv`` and ``results.md`` (RMSE of x, y in m and psi in mrad, over the rows
each estimates), ``alignment.json`` and ``test.png`` (the EKF's path and errors), and prints
the table.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from lbo.core.atomic import atomic_path
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.filters import classical, measure
from lbo.scoring.metrics import rmse
from lbo.sim import hguide
from lbo.sim.logio import TRUTH_COLUMNS, check_log, check_output_path, receiver, write_table

__all__ = ["main", "realdrive", "score"]


def score(log: pd.DataFrame, observers: list[str], vehicle: Any, noise: Any
          ) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
    """RMSE (x m, y m, psi mrad) of the raw fixes and each observer on ``log``, every one
    scored from the log's first course over ground on (before it, a car standing since the
    log began, no single-antenna observer can know its heading).

    Returns the table (one row each: ``estimator, x_m, y_m, psi_mrad, rows``) and the
    estimates (T, 3) by name (NaN where an observer has none yet)."""
    from lbo.serve.observer import Observer

    m = log[["x_m", "y_m", "psi_m"]].to_numpy(dtype=float)
    u = log[["V", "delta"]].to_numpy(dtype=float)
    z = log[list(TRUTH_COLUMNS)].to_numpy(dtype=float)
    r = receiver(log)
    course, _ = measure.course_over_ground(r[:, 3], r[:, 4], r[:, 5], u[:, 0])
    if not np.isfinite(course).any():
        raise LboError("the span never moves fast enough for a course over ground: a single "
                       "antenna tells no heading there, and nothing is scored")
    # scored from the first course over ground: before it no one-antenna observer can know
    # the heading (a car standing since the log began), and every estimator is scored alike
    scored = np.arange(len(log)) >= int(np.argmax(np.isfinite(course)))
    fix = np.isfinite(m[:, :2]).all(1) & scored
    position = rmse(np.column_stack([m[:, :2], z[:, 2]]), z, fix)  # its psi error is 0
    heading = rmse(np.column_stack([z[:, :2], course]), z, np.isfinite(course))
    table = [{"estimator": "raw fixes (heading: course over ground)", "x_m": float(position[0]),
              "y_m": float(position[1]), "psi_mrad": 1e3 * float(heading[2]),
              "rows": int(fix.sum())}]
    runs = [(f"{name}, receiver's accuracy and velocity", name, r, False) for name in observers]
    runs += [("ekf, lbo's R, no velocity", "ekf", None, False),
             ("ekf, receiver's channels, smoothed (RTS, offline)", "ekf", r, True)]
    estimates = {}
    for label, name, channels, smooth in runs:
        obs = Observer.load(name, vehicle, noise)
        est, valid = obs.run(m, u, receiver=channels, smooth=smooth)
        e = rmse(est, z, valid & scored)
        table.append({"estimator": label, "x_m": float(e[0]), "y_m": float(e[1]),
                      "psi_mrad": 1e3 * float(e[2]), "rows": int((valid & scored).sum())})
        estimates[label] = np.where(valid[:, None], est, np.nan)
    return pd.DataFrame(table), estimates


def realdrive(cfg: DictConfig) -> dict[str, Any]:
    """Write the hill drive's span logs and score the classical observers on its test span."""
    from lbo.sim.noise import Noise
    from lbo.sim.vehicle import Vehicle

    observers = list(cfg.observers)
    for name in observers:
        classical.check(str(name), "observers")
    out = Path(str(cfg.output_dir))
    paths = {k: check_output_path(out / f"hill_{k}.parquet") for k in hguide.SPANS}
    check_output_path(out / "results.csv")
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    df = hguide.read()
    alignment = hguide.fit_alignment(df)
    log = hguide.to_log(df, vehicle, alignment)
    parts = hguide.spans(log)
    out.mkdir(parents=True, exist_ok=True)
    for k, part in parts.items():
        check_log(part, f"hill drive, {k} span")
        write_table(part, paths[k])
    table, estimates = score(parts["test"], observers, vehicle, noise)
    write_table(table, out / "results.csv")
    with atomic_path(out / "results.md") as tmp:
        Path(tmp).write_text(_markdown(table))
    with atomic_path(out / "alignment.json") as tmp:
        Path(tmp).write_text(json.dumps({"boresight_mrad": 1e3 * alignment.boresight,
                                         "lever_forward_m": float(alignment.lever[0]),
                                         "lever_left_m": float(alignment.lever[1]),
                                         "latency_s": alignment.latency,
                                         "rms_before_m": alignment.rms_before,
                                         "rms_after_m": alignment.rms_after,
                                         "fixes": alignment.fixes}, indent=1) + "\n")
    test = parts["test"]
    from lbo.core import plots

    best = f"{observers[0]}, receiver's accuracy and velocity"
    plots.save(plots.observed_log(test["t"].to_numpy(), test[["x_m", "y_m", "psi_m"]].to_numpy(),
                                  estimates[best], best, test[list(TRUTH_COLUMNS)].to_numpy()),
               out / "test.png")
    print(f"hill drive: {len(log)} rows at {vehicle.dt:g} s, {int(log['x_m'].notna().sum())} "
          f"fixes; boresight {1e3 * alignment.boresight:+.1f} mrad, lever arm "
          f"{alignment.lever[0]:+.2f} m forward, {alignment.lever[1]:+.2f} m left, latency {alignment.latency:.2f} s (fit on {alignment.fixes} fixes above "
          f"{hguide.FIT_SPEED:g} m/s: RMS offset {alignment.rms_before:.2f} m -> "
          f"{alignment.rms_after:.2f} m)")
    print("spans: " + ", ".join(f"{k} {len(p) * vehicle.dt:.0f} s -> {paths[k]}"
                                for k, p in parts.items()))
    print(f"test span ({len(test) * vehicle.dt:.0f} s), RMSE against the INS/GNSS truth "
          "at the antenna:")
    print(_markdown(table), end="")
    print(f"written: {out / 'results.md'}, {out / 'test.png'}")
    return {"table": table, "alignment": alignment, "paths": paths}


def _markdown(table: pd.DataFrame) -> str:
    lines = ["| estimator | x (m) | y (m) | psi (mrad) |", "|---|---:|---:|---:|"]
    lines += [f"| {r.estimator} | {r.x_m:.2f} | {r.y_m:.2f} | {r.psi_mrad:.1f} |"
              for r in table.itertuples()]
    return "\n".join(lines) + "\n"


main = entry("realdrive", realdrive)


if __name__ == "__main__":
    sys.exit(main())
