"""What one epoch of the gyro EKF's noise fit (``lbo.learn.gyro_fit``) costs, by its parts.

    python benchmarks/bench_gyro_fit.py [--seconds 60] [--logs 1] [--segment 500] [--repeats 5]

``logs`` simulated single-antenna drives with a biased gyro (:func:`lbo.sim.gyro_drive.draw`:
fixes with their reported accuracy, the GNSS velocity, a stop; their truth dropped), each
``seconds`` long, cut into segments of ``segment`` steps. Timed, each the median of
``repeats``, on one torch thread:

- ``segments``: the NumPy gyro EKF run over the logs to start each segment from its state,
  every log in one batch (:func:`lbo.learn.gyro_logs.segments`); with several logs, also one
  log at a time, as a fit ran them before that batch;
- ``forward``: the torch filter over the segments, the innovations' likelihood (no graph);
- ``forward+backward``: the same with its graph, and the gradient of the seven noises;
- ``fit``: :func:`lbo.learn.gyro_fit.fit`, ``--epochs`` Adam steps on the innovations.

The filter's loop runs one step of every segment at once, so its cost grows with ``segment``
(the loop's length), not with the log's: a longer log adds rows to each step's batch.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from lbo.filters.gyro_noise import GyroNoise
from lbo.learn import gyro_fit, gyro_logs
from lbo.models.gyro_filter import GyroFilter
from lbo.sim import gyro_drive

VEHICLE = gyro_drive.VEHICLE
R = np.diag([1.0, 1.0, 0.0174**2])
START = GyroNoise.from_q(np.diag([0.0667**2, 0.0667**2, 0.00113**2]))


def median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--logs", type=int, default=1)
    ap.add_argument("--segment", type=int, default=500)
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    logs = [gyro_drive.draw(j, args.seconds).drop(columns=["x", "y", "psi"])  # no truth
            for j in range(args.logs)]
    seg = gyro_logs.segments(logs, START, VEHICLE, R, args.segment)
    model = GyroFilter(START, VEHICLE.dt, torch.as_tensor(R))

    def forward() -> None:
        with torch.no_grad():
            gyro_fit._innovations(model, seg)

    def backward() -> None:
        model.zero_grad()
        gyro_fit._innovations(model, seg).backward()

    def fit() -> None:
        gyro_fit.fit(logs, logs, VEHICLE, R, START, epochs=args.epochs, segment=args.segment,
                     progress=None, objective="innovations")

    def one_by_one() -> None:
        for log in logs:
            gyro_logs.segments(log, START, VEHICLE, R, args.segment)

    g, t = seg.fix.shape[:2]
    print(f"{args.logs} log(s) of {args.seconds:g} s: {g} segments of {t} steps; torch "
          f"{torch.__version__}, one thread; medians of {args.repeats}")
    parts = [("segments", lambda: gyro_logs.segments(logs, START, VEHICLE, R, args.segment),
              args.repeats)]
    if args.logs > 1:
        parts.append(("segments, one by one", one_by_one, args.repeats))
    for name, fn, repeats in (*parts, ("forward", forward, args.repeats),
                              ("forward+backward", backward, args.repeats),
                              (f"fit, {args.epochs} epochs", fit, max(1, args.repeats // 2))):
        s = median_s(fn, repeats)
        print(f"{name:>20}: {s * 1e3:8.1f} ms" + (f" ({s / t * 1e6:.0f} us a step)"
                                                  if name.startswith("forward") else ""))


if __name__ == "__main__":
    main()
