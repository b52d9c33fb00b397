"""What drawing the measurement noise on the fly costs in training throughput.

    python benchmarks/bench_noise.py [--repeats 5] [--models cnn lstm] [--windows 20 80]

For each model and window on the quick data set (batch 256, CPU), the bare training loop of
``bench_train.py`` runs on batches with the data set's stored measurements
(``train_noise=stored``) and on batches whose measurements are drawn afresh for every
window (``train_noise=paper``: alpha = 1). The two alternate ``repeats`` times; the figure
is the median of the per-pair ratios drawn / stored of the step-median throughput (the
total throughput is printed too). Target: >= 0.90, i.e. drawing costs at most 10 %.
"""

from __future__ import annotations

import argparse
import statistics

import torch
from bench_train import BATCH, SEED, STEPS, bare, compose_cfg

from lbo.learn.datamodule import WindowDataModule
from lbo.learn.draws import AlphaDraw
from lbo.sim.datasets import build, spec_from_cfg

TARGET = 0.90


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--models", nargs="+", default=["cnn", "lstm"])
    ap.add_argument("--windows", nargs="+", type=int, default=[20, 80])
    args = ap.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, batch {BATCH}, "
          f"median of {args.repeats} alternating repeats\n")
    print(f"{'model':<6}{'N':>4}{'stored':>10}{'drawn':>10}{'ratio':>8}"
          f"{'ratio (total)':>15}   samples/s, step-median")
    ok = True
    for m in args.models:
        for n in args.windows:
            cfg = compose_cfg(m, n)
            folder, _, _ = build(spec_from_cfg(cfg), progress=False)
            dms = {"stored": WindowDataModule(folder, n, BATCH, seed=SEED),
                   "drawn": WindowDataModule(folder, n, BATCH, seed=SEED, draw=AlphaDraw(),
                                             sigma=tuple(cfg.noise.measurement_sigma))}
            for dm in dms.values():
                dm.setup("fit")
            norm = dms["stored"].normalisation(cfg.model.features)
            warmup, measured = STEPS.get((m, n), (10, 100))
            runs = {k: [] for k in dms}
            for _ in range(args.repeats):
                for k, dm in dms.items():
                    runs[k].append(bare(cfg, dm, norm, warmup, measured))
            med = {k: statistics.median(r.step_median for r in v) for k, v in runs.items()}
            pair = statistics.median(d.step_median / s.step_median
                                     for s, d in zip(runs["stored"], runs["drawn"]))
            pair_total = statistics.median(d.total / s.total
                                           for s, d in zip(runs["stored"], runs["drawn"]))
            ok &= pair >= TARGET
            print(f"{m:<6}{n:>4}{med['stored']:>10.0f}{med['drawn']:>10.0f}{pair:>8.3f}"
                  f"{pair_total:>15.3f}", flush=True)
    print(f"\nevery drawn/stored ratio >= {TARGET}: {'yes' if ok else 'NO'}")


if __name__ == "__main__":
    main()
