"""A learned peer trained as it runs (:mod:`lbo.learn.sequence`) and scored carried over the
robust test grid, beside the oracle.

    python benchmarks/sequence_peers.py [--model split_kalmannet] [--epochs 4] [--chunk 100]

The robust observer's data set (``data=robust``, generated if missing): its training
trajectories (friction circle and stop-and-go, 40 s each) as sequences, each with its own
alpha drawn uniformly on [0, 6.5] and its own fix period (a fix every 1, 5, 10 or 50 steps:
50, 10, 5 and 1 Hz), fresh every epoch, as the robust observer's windows are; truncated
back-propagation through time in chunks of ``--chunk`` steps; validation on its validation
trajectories at alpha 1, 3 and 6. The trained filter then runs carried from each test
trajectory's first step (every fix taken), and the script prints its NRMSE per alpha beside
the EKF and the oracle EKF, and its ratio to the oracle.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from lbo.learn import sequence
from lbo.models import build_model, carried

RATES = (1, 5, 10, 50)
"""Fix periods (steps) drawn per training sequence: 50, 10, 5 and 1 Hz at 50 Hz."""


def main() -> None:
    from pathlib import Path

    import pandas as pd
    from hydra import compose, initialize_config_dir

    from lbo.core.paths import CONF_DIR
    from lbo.datagen import generate
    from lbo.scoring import grid
    from lbo.sim import schema
    from lbo.sim.datasets import spec_from_cfg

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="split_kalmannet")
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--chunk", type=int, default=100)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("datagen", ["data=robust"])
    spec = spec_from_cfg(cfg)
    folder = Path(generate(cfg))
    sigma = np.asarray(spec.noise.measurement_sigma)
    rng = np.random.default_rng(args.seed)
    tr = schema.to_arrays(schema.read_set(folder / "train.parquet"))
    va = schema.to_arrays(schema.read_set(folder / "val.parquet"))
    te = grid.load_test(folder / "test.parquet")

    def drawn(arr, alphas, every):
        return sequence.draw(arr.z, arr.u, sigma, alphas, every, rng)

    val = drawn(va, rng.choice([1.0, 3.0, 6.0], len(va.z)), np.ones(len(va.z), int))
    torch.manual_seed(args.seed)
    net = build_model(args.model, 400, dt=spec.vehicle.dt, wheelbase=spec.vehicle.wheelbase,
                      measurement_sigma=tuple(sigma), gain=0.3)
    start = time.perf_counter()
    history = []
    for epoch in range(args.epochs):  # fresh draws every epoch, as the windows' are
        train = drawn(tr, rng.uniform(0.0, 6.5, len(tr.z)), rng.choice(RATES, len(tr.z)))
        fit = sequence.fit(net, train, val, 1, args.chunk, args.batch, args.lr,
                           seed=args.seed + epoch, progress=None)
        history.append(fit.validation[-1])
        print(f"epoch {epoch + 1}/{args.epochs}: train {fit.train[0]:.4g}, validation "
              f"{fit.validation[-1]:.4g} (before {fit.validation[0]:.4g}), "
              f"{time.perf_counter() - start:.0f} s", flush=True)
    trained = time.perf_counter() - start
    test = sequence.Sequences(te.m, te.u, te.z)
    centred = test.centred()
    with torch.no_grad():
        est = carried.run(net, torch.as_tensor(centred.m, dtype=torch.float32),
                          torch.as_tensor(centred.u, dtype=torch.float32)).est
    est = est.numpy().astype(float) + (test.z - centred.z)  # back where the set lies
    ref = grid.reference(te, spec.vehicle, spec.noise)
    name = f"{args.model} (sequence-trained, carried)"
    table = grid.classical_table(te, spec.vehicle, spec.noise, ["ekf", "oracle"], ref)
    table = pd.concat([grid.score(name, est, te, ref), table], ignore_index=True)
    nr = table.pivot(index="alpha", columns="observer", values="nrmse")
    nr["ratio to oracle"] = nr[name] / nr["oracle"]
    shown = nr.loc[nr.index.isin([0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0])]
    print(shown.round(3).to_string())
    band = nr["ratio to oracle"][(nr.index >= 0.25) & (nr.index <= 6.0)]
    print(f"ratio to the oracle over alpha 0.25-6: {band.min():.2f}-{band.max():.2f}; "
          f"training {trained / 60:.1f} min ({args.epochs} epochs); parameters "
          f"{sum(p.numel() for p in net.parameters())}")


if __name__ == "__main__":
    main()
