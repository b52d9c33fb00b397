"""Side slip on a real car at the limit: the MBDS run shipped with lbo (:mod:`lbo.sim.sideslip`),
split by time 60/20/20, each classical estimate of beta scored against the INS's on each span.

The linear single-track Kalman filter is told the car's published parameters
(:data:`lbo.sim.sideslip.CAR`) and the noise read off the training span alone
(:meth:`lbo.filters.lateral.LateralNoise.of`); the EKF with saturating tyres the same, and the
friction read off the training span (:func:`lbo.sim.sideslip.friction`); the validation span
shows how its error moves with the friction. Nothing looks at the test span but the scoring.
With ``--slip``, the learned observer of an ``lbo.train model=slip_gru data=sideslip``
checkpoint joins the table and the plot, and its stream is timed a row at a time on one thread
(its network in PyTorch and in ONNX Runtime; the first 100 rows left out, the median and the
99th percentile of the test span's rows). With ``--filter``, the learned filter of an
``lbo.train model=slip_filter data=sideslip`` checkpoint joins them the same way (its stream in
PyTorch), with the share of the test span's rows whose beta lies inside its 2-sigma band.
Writes the markdown tables to stdout and the plot of beta over the test span to ``docs/``.

    python benchmarks/sideslip.py [--slip <slip_gru run>/checkpoints/best.ckpt]
        [--filter <slip_filter run>/checkpoints/best.ckpt] [docs/sideslip.png]
"""

import argparse
import dataclasses
import time

import numpy as np
import torch

from lbo.core import plots
from lbo.filters.lateral import (
    LateralNoise,
    kinematic_beta,
    linear_single_track,
    nonlinear_single_track,
)
from lbo.models import slip, slip_filter
from lbo.serve import lateral
from lbo.sim import sideslip

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("plot", nargs="?", default="docs/sideslip.png")
parser.add_argument("--slip", help="a model=slip_gru checkpoint to score and time")
parser.add_argument("--filter", help="a model=slip_filter checkpoint to score and time")
args = parser.parse_args()
out = args.plot
learned = slip.load(args.slip) if args.slip else None
lfilter = slip_filter.load(args.filter) if args.filter else None
FILTER = "learned: linear KF, tyres and noise learned (slip_filter)"
spans = sideslip.split(sideslip.example())
noise = LateralNoise.of(*sideslip.observed(spans["train"]))
mu = sideslip.friction(spans["train"])
car = dataclasses.replace(sideslip.CAR, mu=mu)
print(f"read off the train span: {noise}, friction {mu:.3f}")


def deg_rms(err: np.ndarray) -> float:
    return float(np.rad2deg(np.sqrt(np.mean(err**2))))


rows, test_estimates = [], {}
for name, span in spans.items():
    vx, delta, y = sideslip.observed(span)
    beta = span["beta"].to_numpy()
    start = time.perf_counter()
    lkf = linear_single_track(vx, delta, y, sideslip.CAR, noise, sideslip.DT)
    seconds = time.perf_counter() - start
    start = time.perf_counter()
    ekf = nonlinear_single_track(vx, delta, y, car, noise, sideslip.DT)
    nonlinear = time.perf_counter() - start
    estimates = {"zero (straight ahead)": np.zeros_like(beta),
                 "kinematic bicycle": kinematic_beta(delta, sideslip.CAR),
                 "linear single-track KF": lkf.beta,
                 f"single-track EKF, tyres saturating at mu = {mu:.2f}": ekf.beta}
    if learned is not None:
        estimates["learned: linear KF + GRU correction (slip_gru)"] = learned.run(vx, delta, y).beta
    if lfilter is not None:
        filtered = lfilter.run(vx, delta, y)
        estimates[FILTER] = filtered.beta
        inside = np.abs(filtered.beta - beta) <= 2 * np.sqrt(filtered.P[:, 0, 0])
        print(f"{name}: slip_filter's beta inside its 2-sigma band on {inside.mean():.1%} of "
              "the rows")
    for observer, est in estimates.items():
        rows.append((name, observer, deg_rms(est - beta), np.rad2deg(np.abs(est - beta).max())))
    print(f"{name}: {len(span)} rows, {span['t'].iloc[0]:.2f}-{span['t'].iloc[-1]:.2f} s; "
          f"the linear filter {1e6 * seconds / len(span):.0f} us a row, the EKF "
          f"{1e6 * nonlinear / len(span):.0f} us a row")
    if name == "test":
        test_estimates = {"INS (reference)": beta, **estimates}
        t = span["t"].to_numpy()

print("\n| span | estimate of beta | RMSE (deg) | largest error (deg) |")
print("|---|---|---|---|")
for name, observer, rmse, worst in rows:
    print(f"| {name} | {observer} | {rmse:.2f} | {worst:.2f} |")

streams = ([(f"slip_gru (window {learned.window})", learned, lateral.ENGINES)]
           if learned is not None else [])
streams += [("slip_filter", lfilter, lateral.ENGINES)] if lfilter is not None else []
for label, observer, engines in streams:
    torch.set_num_threads(1)
    vx, delta, y = sideslip.observed(spans["test"])
    print(f"\n{label}, one row at a time on one thread:")
    print("| its network in | median (us) | 99th percentile (us) |\n|---|---|---|")
    for engine in engines:
        stream, took = lateral.stream(observer, engine), []
        for row in zip(vx, delta, y[:, 0], y[:, 1]):
            start = time.perf_counter()
            stream.step(*row)
            took.append(time.perf_counter() - start)
        us = 1e6 * np.array(took[100:])
        print(f"| {engine} | {np.median(us):.0f} | {np.percentile(us, 99):.0f} |")

val = spans["val"]
print("\n| friction mu | beta RMSE on the validation span (deg) |")
print("|---|---|")
for m in sorted({1.0, round(mu, 2), 1.7, 100.0}):
    est = nonlinear_single_track(*sideslip.observed(val), dataclasses.replace(car, mu=m), noise,
                                 sideslip.DT)
    print(f"| {m:g} | {deg_rms(est.beta - val['beta'].to_numpy()):.2f} |")

import matplotlib.pyplot as plt  # noqa: E402  (after the numbers: the plot is the last step)

fig, ax = plt.subplots(figsize=(10, 3.6))
for observer, est in test_estimates.items():
    ax.plot(t, np.rad2deg(est), lw=1.6 if observer.startswith("INS") else 0.9,
            color="k" if observer.startswith("INS") else None, label=observer)
ax.set_xlabel("t (s)")
ax.set_ylabel("side slip beta (deg)")
ax.set_title("MBDS side-slip run, test span (the last 20%)")
ax.legend(ncol=4, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2))
print(f"\nplot: {plots.save(fig, out)}")
