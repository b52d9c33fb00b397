"""Training throughput: a bare PyTorch loop against Lightning, same network, same data.

    python benchmarks/bench_train.py [--repeats 5] [--models cnn lstm] [--windows 20 80]
                                     [--threads T] [--set optimizer.fused=false ...]

For each model (its default config from conf/model/) and window N, on the quick data set,
batch size 256, on the CPU:

- bare: ``WindowNet`` + ``WindowDataModule.train_dataloader()`` + the training config's
  optimizer (``conf/train.yaml``: Adam, lr 1e-3, fused); loss = net.loss(*batch); zero_grad;
  backward; step.
- lightning: ``TrainingModule`` with the same model, fitted by a minimal ``lightning.Trainer``
  (no logger, checkpoint, progress bar, model summary or validation) on the same datamodule.

Both run ``warm-up + measured`` steps from the same seed (same weights, same batches: the
losses agree step by step). Timing: one clock reading at the end of every step (after the
optimiser step in the bare loop; in a Callback's ``on_train_batch_end`` for Lightning, so
Trainer setup and teardown are excluded). The ``measured`` periods between consecutive
readings after the warm-up are whole loop iterations: batch fetch, forward, backward, step
and, for Lightning, all its per-step hooks and bookkeeping. Two figures come from them:

- total: batch * measured / sum(periods), the plain wall-clock throughput;
- step-median: batch / median(period), which ignores the steps another process stalled.
  On a shared 2-core machine torch's two OpenMP threads can stall for ~1 s per step while a
  neighbour holds a core, so the total figure of one run can drop 10-100x at random
  (``--threads 1`` is slower on an idle machine but does not stall).

A run stops measuring after CAP_S seconds (a stalled machine) and keeps the steps it has.

The two methods alternate ``repeats`` times (5). Throughputs are medians over the repeats;
each ratio is the median of the per-pair ratios lightning / bare, since the two runs of a pair
are adjacent in time and share the machine's drift. Target: ratio >= 0.85.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import time
import warnings
from dataclasses import dataclass

import lightning as L
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

import lbo.core.paths
from lbo.learn.builders import build_net
from lbo.learn.datamodule import WindowDataModule
from lbo.learn.lightning_module import TrainingModule
from lbo.models.net import WindowNet
from lbo.sim.datasets import build, spec_from_cfg

BATCH = 256
SEED = 0
TARGET = 0.85
# (warm-up, measured) steps; the LSTM at N=80 is ~10x slower than the CNN at N=20.
STEPS = {("cnn", 20): (10, 100), ("cnn", 80): (10, 100),
         ("lstm", 20): (10, 100), ("lstm", 80): (5, 40)}
# Stop a run's measurement after this many seconds (a stalled, shared CPU), keeping its steps.
CAP_S = 8.0
STALL = 3.0  # a step longer than STALL x the run's median step counts as stalled


@dataclass
class Run:
    periods: list[float]  # seconds per measured step
    losses: list[float]   # loss of each measured step
    threads: int          # torch.get_num_threads() inside the loop

    @property
    def total(self) -> float:
        return BATCH * len(self.periods) / sum(self.periods)

    @property
    def step_median(self) -> float:
        return BATCH / statistics.median(self.periods)

    @property
    def stalled(self) -> int:
        med = statistics.median(self.periods)
        return sum(p > STALL * med for p in self.periods)


def compose_cfg(model: str, window: int, overrides: list[str] | None = None) -> DictConfig:
    with initialize_config_dir(str(lbo.core.paths.CONF_DIR), version_base="1.3"):
        return compose("train", [f"model={model}", f"window={window}", "data=quick",
                                 *(overrides or [])])


def _sync(device: torch.device) -> None:
    """Wait for the GPU's queued work, so that a clock reading ends a whole step."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _periods(stamps: list[float]) -> list[float]:
    return [b - a for a, b in zip(stamps, stamps[1:])]


def bare(cfg: DictConfig, dm: WindowDataModule, norm: dict, warmup: int, measured: int) -> Run:
    """The plain loop over ``warmup + measured`` steps."""
    torch.manual_seed(SEED)
    model = OmegaConf.to_container(cfg.model, resolve=True)
    kwargs = {k: v for k, v in model.items() if k != "name"}
    net = WindowNet(model["name"], cfg.model.window, cfg.model.features, **kwargs).to(dm.device)
    net.set_normalisation(**norm)
    net.train()
    opt = instantiate(cfg.optimizer)(params=net.parameters())
    stamps: list[float] = []
    losses: list[float] = []
    for step, batch in enumerate(dm.train_dataloader()):
        loss = net.loss(*batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step >= warmup - 1:
            _sync(dm.device)
            stamps.append(time.perf_counter())
            losses.append(loss.item())
        if step == warmup + measured - 1 or (stamps and stamps[-1] - stamps[0] > CAP_S):
            break
    return Run(_periods(stamps), losses[1:], torch.get_num_threads())


class StepClock(L.Callback):
    """Clock readings at ``on_train_batch_end`` from the last warm-up batch on."""

    def __init__(self, warmup: int) -> None:
        self.warmup = warmup
        self.stamps: list[float] = []
        self.losses: list[float] = []
        self.threads = 0

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if batch_idx >= self.warmup - 1:
            _sync(pl_module.device)
            self.stamps.append(time.perf_counter())
            self.losses.append(float(outputs["loss"]))
            self.threads = torch.get_num_threads()
            if self.stamps[-1] - self.stamps[0] > CAP_S:
                trainer.should_stop = True


def lightning(cfg: DictConfig, dm: WindowDataModule, norm: dict, warmup: int,
              measured: int) -> Run:
    """``Trainer.fit`` for ``warmup + measured`` steps."""
    torch.manual_seed(SEED)
    module = TrainingModule(OmegaConf.to_container(cfg.model, resolve=True), cfg.model.window,
                            cfg.model.features, optimizer=instantiate(cfg.optimizer))
    module.observer.set_normalisation(**norm)
    clock = StepClock(warmup)
    trainer = L.Trainer(accelerator="gpu" if dm.device.type == "cuda" else "cpu", devices=1,
                        max_steps=warmup + measured,
                        logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, num_sanity_val_steps=0,
                        limit_val_batches=0, callbacks=[clock])
    trainer.fit(module, datamodule=dm)
    if len(clock.stamps) < 2:
        raise RuntimeError("Lightning stopped before the first measured step ended")
    return Run(_periods(clock.stamps), clock.losses[1:], clock.threads)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--models", nargs="+", default=["cnn", "lstm"])
    ap.add_argument("--windows", nargs="+", type=int, default=[20, 80])
    ap.add_argument("--threads", type=int, default=None,
                    help="torch.set_num_threads(T) first (default: torch's own choice)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (batches made there)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="training config overrides, e.g. optimizer.fused=false")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    # Lightning's banner ("GPU available: ...") and its hints are noise here.
    logging.getLogger("lightning.pytorch").setLevel(logging.ERROR)
    logging.getLogger("lightning.fabric").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")

    t0 = time.perf_counter()
    print(f"torch {torch.__version__}, lightning {L.__version__}, device {args.device}, "
          f"torch.get_num_threads() = {torch.get_num_threads()}, os.cpu_count() = "
          f"{os.cpu_count()}, batch size {BATCH}, load average {os.getloadavg()[0]:.2f}")
    print("timing: clock at the end of every step (Lightning: a Callback's on_train_batch_end, "
          "so Trainer setup/teardown are excluded); figures from the measured step periods "
          f"(see the docstring); median of {args.repeats} alternating repeats.\n")
    if os.getloadavg()[0] >= 1.0:
        print(f"WARNING: load average {os.getloadavg()[0]:.2f} before starting: other processes "
              "hold the CPU, so expect stalled steps and unreliable figures (try --threads 1, "
              "or run on an idle machine).\n")

    rows = []
    for m in args.models:
        for n in args.windows:
            cfg = compose_cfg(m, n, args.set)
            folder, _, _ = build(spec_from_cfg(cfg), progress=False)
            dm = WindowDataModule(folder, n, BATCH, seed=SEED, device=args.device)
            dm.setup("fit")
            # the statistics of the windows as this net reads them (its features)
            norm = dm.normalisation(build_net(cfg), cfg.model.normalisation)
            warmup, measured = STEPS.get((m, n), (10, 100))
            runs: dict[str, list[Run]] = {"bare": [], "lightning": []}
            for _ in range(args.repeats):
                runs["bare"].append(bare(cfg, dm, norm, warmup, measured))
                runs["lightning"].append(lightning(cfg, dm, norm, warmup, measured))
            med = {k: (statistics.median(r.total for r in v),
                       statistics.median(r.step_median for r in v)) for k, v in runs.items()}
            # the loss of the last step both runs of a pair completed
            dloss = max(abs(b.losses[k] - lt.losses[k]) for b, lt in zip(*runs.values())
                        for k in [min(len(b.losses), len(lt.losses)) - 1])
            threads = sorted({r.threads for v in runs.values() for r in v})
            steps = min(len(r.periods) for v in runs.values() for r in v)
            stalled = {k: sum(r.stalled for r in v) for k, v in runs.items()}
            # ratios of the two runs of each pair (adjacent in time), then their median: the
            # machine's speed drifts between repeats, and both runs of a pair share it
            pair = {k: statistics.median(getattr(lt, k) / getattr(b, k)
                                         for b, lt in zip(runs["bare"], runs["lightning"]))
                    for k in ("total", "step_median")}
            rows.append((m, n, warmup, measured, steps, med, pair, dloss, threads, stalled))
            for k, v in runs.items():
                print(f"  {m} N={n} {k:<9} total {[round(r.total) for r in v]}, step-median "
                      f"{[round(r.step_median) for r in v]} samples/s, stalled steps "
                      f"{[r.stalled for r in v]}", flush=True)

    print(f"\n{'':24}{'---- total (samples/s) ----':>30}{'---- step-median (samples/s) --':>33}")
    print(f"{'model':<6}{'N':>4}{'steps':>9}{'stalls':>8}{'bare':>10}{'lightning':>11}"
          f"{'ratio':>8}{'bare':>10}{'lightning':>11}{'ratio':>8}{'+ms/step':>10}"
          f"{'|dloss|':>9}  threads")
    ok_total = ok_step = True
    for m, n, w, s, got, med, pair, dloss, threads, stalled in rows:
        (bt, bs), (lt, ls) = med["bare"], med["lightning"]
        ok_total &= pair["total"] >= TARGET
        ok_step &= pair["step_median"] >= TARGET
        steps = f"{w}+{s}" if got == s else f"{w}+{got}*"
        # the per-step time Lightning adds, from the step medians
        overhead_ms = (BATCH / ls - BATCH / bs) * 1e3
        print(f"{m:<6}{n:>4}{steps:>9}{stalled['bare']:>4}/{stalled['lightning']:<3}{bt:>10.0f}"
              f"{lt:>11.0f}{pair['total']:>8.3f}{bs:>10.0f}{ls:>11.0f}{pair['step_median']:>8.3f}"
              f"{overhead_ms:>10.2f}{dloss:>9.1e}  {threads}")
    print("\nsteps: warm-up + measured (* = a run hit the "
          f"{CAP_S:.0f} s cap; fewest measured shown); stalls: steps > {STALL:.0f}x the run's "
          "median, bare/lightning, over all repeats;\n|dloss|: loss at the last step both runs "
          "of a pair completed, bare vs Lightning (~0: the same work)")
    print(f"every lightning/bare ratio >= {TARGET}: total {'yes' if ok_total else 'NO'}, "
          f"step-median {'yes' if ok_step else 'NO'}")
    print(f"load average {os.getloadavg()[0]:.2f}; total time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
