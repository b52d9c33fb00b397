"""A filter trained carried: how long one step of truncated back-propagation takes, eager and
compiled (``compile=true``).

    python benchmarks/bench_carried.py [--batch 128] [--chunk 100] [--repeats 5]
                                       [--threads 1 2] [--models dynamic robust]

A step of the carried filter is a few hundred operations on (B, 3, 3) tensors; eager PyTorch
spends most of it dispatching them. For each model and thread count, in a process of its own,
one batch of B straight drives of two chunks is trained (a forward, a backward and an Adam
step per chunk, the Gaussian NLL term on) ``repeats`` times after one untimed batch (which
compiles, for the compiled step); the figures are medians in milliseconds per time step:

- ``dynamic``: the car-that-slips observer (``experiment=dynamic_carried``: single-track
  body, GNSS drift states, N = 400);
- ``robust``: the robust observer (kinematic bicycle, the fix channel, N = 40).

``compile s`` is the first batch's extra time: torch.compile at work (seconds once torch's
cache holds the step).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

MODELS = {"dynamic": {"window": 400, "body": "single_track", "drift": True},
          "robust": {"window": 40, "fixes": True}}


def drives(b: int, t: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """b straight drives of t steps at 5-15 m/s, fixes at alpha = 1 (float32 m, u, z)."""
    from lbo.learn.sequence import draw
    from lbo.sim.noise import Noise
    from lbo.sim.vehicle import Vehicle

    rng = np.random.default_rng(seed)
    psi, v = rng.uniform(-np.pi, np.pi, b), rng.uniform(5, 15, b)
    time_s = np.arange(t) * Vehicle().dt
    z = np.stack([v[:, None] * np.cos(psi)[:, None] * time_s,
                  v[:, None] * np.sin(psi)[:, None] * time_s,
                  np.broadcast_to(psi[:, None], (b, t))], -1)
    u = np.stack([np.broadcast_to(v[:, None], (b, t)), np.zeros((b, t))], -1)
    seq = draw(z, u, np.array(Noise.preset("paper").measurement_sigma), np.ones(b),
               np.ones(b, dtype=int), rng).centred()
    return tuple(torch.as_tensor(a, dtype=torch.float32) for a in (seq.m, seq.u, seq.z))


def case(model: str, threads: int, compiled: bool, batch: int, chunk: int,
         repeats: int) -> dict[str, float]:
    """Median ms per time step of training ``model`` carried, and the first batch's extra s."""
    from lbo.learn.sequence import train_batch
    from lbo.models.carried import sequence_model
    from lbo.models.net import WindowNet

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    spec = dict(MODELS[model])
    window = spec.pop("window")
    net = WindowNet("filternet", window, features="frame", **spec).net
    carried = sequence_model(net, compiled)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)

    def step(loss: torch.Tensor) -> None:
        opt.zero_grad()
        loss.backward()
        opt.step()

    m, u, z = drives(batch, 2 * chunk)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        train_batch(carried, m, u, z, chunk, step, nll=0.1)
        times.append(time.perf_counter() - start)
    per_step = statistics.median(times[1:]) / (2 * chunk)
    return {"ms": 1e3 * per_step, "first_s": times[0] - 2 * chunk * per_step}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--chunk", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--case", nargs=3, metavar=("MODEL", "THREADS", "COMPILED"),
                        help=argparse.SUPPRESS)  # one case, in this process
    args = parser.parse_args()
    if args.case:
        model, threads, compiled = args.case
        print(json.dumps(case(model, int(threads), compiled == "1", args.batch, args.chunk,
                              args.repeats)))
        return
    print(f"carried training, B = {args.batch}, chunks of {args.chunk} steps, median of "
          f"{args.repeats} batches, ms per time step ({torch.__version__}, CPU)")
    print(f"{'model':>8} {'threads':>7} {'eager':>8} {'compiled':>9} {'ratio':>6} "
          f"{'compile s':>9}")
    for model in args.models:
        for threads in args.threads:
            got = []
            for compiled in ("0", "1"):  # each in a fresh process: its own threads and caches
                out = subprocess.run(
                    [sys.executable, __file__, "--case", model, str(threads), compiled,
                     "--batch", str(args.batch), "--chunk", str(args.chunk),
                     "--repeats", str(args.repeats)],
                    capture_output=True, text=True, check=True)
                got.append(json.loads(out.stdout.strip().splitlines()[-1]))
            eager, fast = got
            print(f"{model:>8} {threads:>7} {eager['ms']:>8.2f} {fast['ms']:>9.2f} "
                  f"{eager['ms'] / fast['ms']:>6.1f} {fast['first_s']:>9.0f}")


if __name__ == "__main__":
    main()
