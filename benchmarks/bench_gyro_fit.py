"""What one epoch of the gyro EKF's noise fit (``lbo.learn.gyro_fit``) costs, by its parts.

    python benchmarks/bench_gyro_fit.py [--seconds 60] [--segment 500] [--repeats 5]

A simulated single-antenna drive with a biased gyro (:func:`lbo.sim.gyro_drive.draw`: fixes
with their reported accuracy, the GNSS velocity, a stop; its truth dropped), ``seconds``
long, cut into segments of ``segment`` steps. Timed, each the median of ``repeats``, on one
torch thread:

- ``segments``: the NumPy gyro EKF run over the log to start each segment from its state;
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

from lbo.filters.gyro import GyroNoise
from lbo.learn import gyro_fit
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
    ap.add_argument("--segment", type=int, default=500)
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    log = gyro_drive.draw(0, args.seconds).drop(columns=["x", "y", "psi"])  # no truth
    seg = gyro_fit.segments(log, START, VEHICLE, R, args.segment)
    model = GyroFilter(START, VEHICLE.dt, torch.as_tensor(R))

    def forward() -> None:
        with torch.no_grad():
            gyro_fit._innovations(model, seg)

    def backward() -> None:
        model.zero_grad()
        gyro_fit._innovations(model, seg).backward()

    def fit() -> None:
        gyro_fit.fit(log, log, VEHICLE, R, START, epochs=args.epochs, segment=args.segment,
                     progress=None, objective="innovations")

    g, t = seg.fix.shape[:2]
    print(f"{args.seconds:g} s log: {g} segments of {t} steps; torch {torch.__version__}, "
          f"one thread; medians of {args.repeats}")
    for name, fn, repeats in (("segments", lambda: gyro_fit.segments(
            log, START, VEHICLE, R, args.segment), args.repeats), ("forward", forward,
            args.repeats), ("forward+backward", backward, args.repeats),
            (f"fit, {args.epochs} epochs", fit, max(1, args.repeats // 2))):
        s = median_s(fn, repeats)
        print(f"{name:>18}: {s * 1e3:8.1f} ms" + (f" ({s / t * 1e6:.0f} us a step)"
                                                  if name.startswith("forward") else ""))


if __name__ == "__main__":
    main()
