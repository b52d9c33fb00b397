"""Per-step latency of an observer in a control loop, on one CPU thread.

    python benchmarks/bench_latency.py [--steps 2000] [--repeats 3] [--one-process]

Observers: the CNN at N=60 and the LSTM at N=80 (the paper's best windows) in PyTorch eager,
TorchScript and ONNX Runtime, the robust observer (the window filter at N=400) in its window
form (PyTorch; TorchScript and ONNX Runtime cost the same order) and in its recursive form (all
three engines), the car-that-slips observer (the window filter with the single-track body and
the drift states, ``experiment=dynamic``) in its recursive form, and the EKF. One step is
one call of ``Observer.step``, as a 50 Hz loop makes it: the sample goes into the ring
buffer, the window (1, N, 5) is taken as a view, the network (feature transform and
normalisation included) runs on it. The networks have random (untrained) weights: the latency
does not depend on their values.

Each repeat resets the observer, feeds it a simulated drive of ``warm-up + steps`` samples and
times the last ``steps`` calls one by one (the warm-up fills the window, so every timed
call runs the network). The table gives p50 and p99 of these per-call times, each the median
over ``repeats``. torch and ONNX Runtime use one intra-op thread. Each row runs in a Python
process of its own, as a control loop runs its one observer: timed after the rows before it
in one process (``--one-process``), the recursive ONNX steps measured up to 1.8 times slower
at p50 (the leftovers of the earlier rows, not the step's own cost).
Targets: CNN p99 < 1 ms in every engine; the robust observer's recursive form p99 < 1 ms in
ONNX Runtime and < 2 ms in PyTorch; the car-that-slips observer's < 1 ms in ONNX Runtime; the
budget at 50 Hz is 20 ms.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterator

import numpy as np
import onnxruntime
import torch

from lbo.models.net import WindowNet
from lbo.serve.observer import Observer
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle, measure, simulate

WARM_UP = 200
TARGET_MS = 1.0
BUDGET_MS = 20.0
ROBUST_WINDOW = 400
ROBUST = f"robust N={ROBUST_WINDOW}, recursive"
SLIPS = f"car that slips N={ROBUST_WINDOW}, recursive"
TARGETS_RECURSIVE_MS = {(ROBUST, "onnx"): 1.0, (ROBUST, "torch"): 2.0, (SLIPS, "onnx"): 1.0}


def truth(steps: int, rng: np.random.Generator, slow: float = 1.0
          ) -> tuple[np.ndarray, np.ndarray]:
    """A simulated drive's true states (T, 3) and smooth inputs (T, 2): speed 12 +- 3 m/s and
    steering +-0.1 rad, sines of 900 and 400 steps, ``slow`` times longer."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    k = np.arange(steps) / slow
    u = np.stack([12.0 + 3.0 * np.sin(2 * np.pi * k / 900), 0.1 * np.sin(2 * np.pi * k / 400)],
                 axis=1)
    z = simulate(np.zeros((1, 3)), u[None], vehicle.dt, vehicle.wheelbase,
                 noise.process_sigma, rng)[0]
    return z, u


def drive(steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A simulated drive: (T, 3) measurements at alpha=1 and (T, 2) smooth inputs."""
    rng = np.random.default_rng(seed)
    z, u = truth(steps, rng)
    return measure(z, Noise.preset("paper").meas(1.0), rng), u


def latency(obs: Observer, m: np.ndarray, u: np.ndarray, steps: int) -> np.ndarray:
    """Per-call times (ms) of the last ``steps`` calls of ``obs.step`` over the drive."""
    obs.reset()
    times = np.empty(steps)
    start = len(m) - steps
    for k in range(start):
        obs.step(m[k], u[k])
    clock = time.perf_counter_ns
    for k in range(start, len(m)):
        t0 = clock()
        obs.step(m[k], u[k])
        times[k - start] = clock() - t0
    return times / 1e6


def observers() -> Iterator[tuple[str, str, Callable[[], Observer]]]:
    """(label, engine, a maker of its observer) for every row of the table: the networks are
    drawn in this order whichever rows are made, so each row's weights are the same alone."""
    torch.manual_seed(0)
    for model, window in (("cnn", 60), ("lstm", 80)):
        net = WindowNet(model, window).eval()
        for engine in ("torch", "torchscript", "onnx"):
            yield f"{model.upper()} N={window}", engine, \
                lambda net=net, engine=engine: Observer.from_net(net, engine=engine)
    # the robust observer: fix channel, as experiment=robust trains it
    robust = WindowNet("filternet", ROBUST_WINDOW, features="frame", fixes=True).eval()
    yield f"robust N={ROBUST_WINDOW}, window form", "torch", \
        lambda: Observer.from_net(robust, form="window")
    for engine in ("torch", "torchscript", "onnx"):
        yield ROBUST, engine, \
            lambda engine=engine: Observer.from_net(robust, engine=engine, form="recursive")
    slips = WindowNet("filternet", ROBUST_WINDOW, features="frame", body="single_track",
                      drift=True).eval()
    for engine in ("torch", "onnx"):
        yield SLIPS, engine, \
            lambda engine=engine: Observer.from_net(slips, engine=engine, form="recursive")
    yield "EKF", "numpy", lambda: Observer.load("ekf")


def time_row(label: str, make: Callable[[], Observer], steps: int, repeats: int
             ) -> tuple[float, float, int]:
    """p50 and p99 (ms) of one row's steps, each the median over ``repeats``, and the number
    of timed steps (fewer for the window form, ~100 ms a step)."""
    obs = make()
    m, u = drive(WARM_UP + steps)
    window_form = "window form" in label
    steps = min(steps, 100) if window_form else steps
    # the window form's warm-up: one window, not the whole drive (65 ms a step)
    start = len(m) - (ROBUST_WINDOW + steps if window_form else len(m))
    runs = [latency(obs, m[start:], u[start:], steps) for _ in range(repeats)]
    return (float(np.median([np.percentile(r, 50) for r in runs])),
            float(np.median([np.percentile(r, 99) for r in runs])), steps)


def rows(steps: int, repeats: int, one_process: bool
         ) -> Iterator[tuple[str, str, float, float, int]]:
    """(label, engine, p50, p99, timed steps) of every row, each timed in a process of its
    own (``--row``) unless ``one_process``."""
    for i, (label, engine, make) in enumerate(observers()):
        if one_process:
            yield label, engine, *time_row(label, make, steps, repeats)
            continue
        res = subprocess.run([sys.executable, __file__, "--row", str(i), "--steps", str(steps),
                              "--repeats", str(repeats)], capture_output=True, text=True)
        if res.returncode != 0:
            raise SystemExit(f"row {label} ({engine}) failed:\n{res.stderr[-2000:]}")
        p50, p99, n = json.loads(res.stdout.strip().splitlines()[-1])
        yield label, engine, p50, p99, n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="timed steps per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--one-process", action="store_true",
                        help="time every row in this process, one after another")
    parser.add_argument("--row", type=int, help=argparse.SUPPRESS)  # a child's one row
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.row is not None:
        label, _, make = list(observers())[args.row]
        print(json.dumps(time_row(label, make, args.steps, args.repeats)))
        return
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if "model name" in line)
    except (OSError, StopIteration):
        pass
    print(f"per-step latency of Observer.step, one thread ({cpu}; torch {torch.__version__}, "
          f"onnxruntime {onnxruntime.__version__})")
    print(f"{args.steps} timed steps after {WARM_UP} warm-up, p50/p99 = median over "
          f"{args.repeats} repeats; networks untrained (random weights); "
          f"{'every row in one process' if args.one_process else 'a process per row'}")
    print()
    print("| observer | engine | p50 (ms) | p99 (ms) |")
    print("|---|---|---|---|")
    cnn_p99, recursive_p99 = [], {}
    for label, engine, p50, p99, steps in rows(args.steps, args.repeats, args.one_process):
        window_form = "window form" in label
        if label.startswith("CNN"):
            cnn_p99.append(p99)
        if "recursive" in label:
            recursive_p99[label, engine] = p99
        print(f"| {label} | {engine} | {p50:.3f} | {p99:.3f} |"
              + (f" ({steps} timed steps)" if window_form else ""), flush=True)
    print()
    worst = max(cnn_p99)
    print(f"CNN N=60 p99 < {TARGET_MS:g} ms in every engine: "
          f"{'met' if worst < TARGET_MS else 'NOT met'} (worst {worst:.3f} ms); "
          f"budget at 50 Hz: {BUDGET_MS:g} ms")
    for (label, engine), target in TARGETS_RECURSIVE_MS.items():
        p99 = recursive_p99[label, engine]
        print(f"{label}, {engine} p99 < {target:g} ms: "
              f"{'met' if p99 < target else 'NOT met'} ({p99:.3f} ms)")


if __name__ == "__main__":
    main()
