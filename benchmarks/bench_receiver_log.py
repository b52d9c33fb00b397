"""A one-hour receiver log through ``python -m lbo.observe``: the wall time of each classical
observer, end to end (read, check, filter, write).

    python benchmarks/bench_receiver_log.py [--hours 1] [--repeats 3] [--fix-rate 5]
        [--observers ekf,<robust checkpoint>] [--engines torch,onnx]

The log: 180,000 rows at 50 Hz (one hour) of a simulated drive, single-antenna fixes (no
heading) at ``--fix-rate`` Hz with the accuracy the receiver reports (``sx_m, sy_m``) and its
velocity (``ve_m, vn_m, sv_m``), a gyro (``r_m``) at every row, the truth columns included.
Each observer runs as a user runs it, in its own process; the table gives the median over
``repeats`` and the time per row. Targets: the EKF under 10 s on a 2-core CPU, a learned
observer (``--observers ekf,<robust checkpoint>``: the robust observer's recursive form, which
reads the receiver's channels) under 60 s. A learned observer runs once per engine of
``--engines`` (``engine=`` of ``lbo.observe``).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from bench_latency import truth
from bench_observe import timed

from lbo.sim.vehicle import Vehicle

TARGET_S = {"ekf": 10.0, "learned": 60.0}
"""Targets for one hour: the EKF's, and any learned observer's (a checkpoint or a run id)."""
CLASSICAL = ("ekf", "oracle", "adaptive", "ukf", "gyro")


def receiver_log(rows: int, fix_rate: float, seed: int = 0) -> pd.DataFrame:
    """A simulated drive of ``rows`` 50 Hz rows as a receiver logs it (see the docstring)."""
    vehicle = Vehicle()
    rng = np.random.default_rng(seed)
    k = np.arange(rows)
    z, u = truth(rows, rng, slow=10.0)
    fix = k % int(round(1 / (fix_rate * vehicle.dt))) == 0
    sigma = rng.uniform(0.3, 1.5, size=rows)
    vel = u[:, :1] * np.column_stack([np.cos(z[:, 2]), np.sin(z[:, 2])])
    df = pd.DataFrame({"t": k * vehicle.dt, "x_m": z[:, 0] + sigma * rng.standard_normal(rows),
                       "y_m": z[:, 1] + sigma * rng.standard_normal(rows), "psi_m": np.nan,
                       "sx_m": sigma, "sy_m": sigma,
                       "ve_m": vel[:, 0] + 0.05 * rng.standard_normal(rows),
                       "vn_m": vel[:, 1] + 0.05 * rng.standard_normal(rows), "sv_m": 0.05,
                       "r_m": u[:, 0] * np.tan(u[:, 1]) / vehicle.wheelbase
                       + 0.01 * rng.standard_normal(rows),
                       "V": u[:, 0], "delta": u[:, 1], "x": z[:, 0], "y": z[:, 1],
                       "psi": z[:, 2]})
    cols = ["x_m", "y_m", "sx_m", "sy_m", "ve_m", "vn_m", "sv_m"]
    df.loc[~fix, cols] = np.nan
    return df


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fix-rate", type=float, default=5.0)
    ap.add_argument("--observers", default="ekf,ukf,adaptive,gyro")
    ap.add_argument("--engines", default="torch,onnx",
                    help="engines a learned observer runs on, each its own row")
    args = ap.parse_args()
    rows = int(round(args.hours * 3600 / Vehicle().dt))
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "hour.parquet"
        receiver_log(rows, args.fix_rate).to_parquet(log)
        print(f"{rows} rows ({args.hours:g} h at 50 Hz), fixes at {args.fix_rate:g} Hz with "
              f"sx_m, sy_m, ve_m, vn_m, sv_m; {platform.processor() or platform.machine()}, "
              f"median of {args.repeats}")
        print("| observer | wall (s) | per row (us) | target |")
        print("|---|---:|---:|---|")
        runs = [(name, None) if name in CLASSICAL else (name, engine)
                 for name in args.observers.split(",")
                 for engine in ([None] if name in CLASSICAL else args.engines.split(","))]
        for name, engine in runs:
            wall = statistics.median([timed(name, log, Path(tmp) / "est.parquet",
                                            [f"engine={engine}"] if engine else [], cwd=None)
                                      for _ in range(args.repeats)])
            kind = name if name in CLASSICAL else "learned"
            target = TARGET_S.get(kind) if args.hours == 1 else None  # set for one hour
            verdict = "" if target is None else (f"< {target:g} s: "
                                                 + ("met" if wall < target else "missed"))
            label = name if engine is None else f"learned ({Path(name).name}, {engine})"
            print(f"| {label} | {wall:.1f} | {1e6 * wall / rows:.0f} | {verdict} |")


if __name__ == "__main__":
    main()
