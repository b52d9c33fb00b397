"""Where a quick training step spends its time, part by part.

    python benchmarks/profile_train.py [--steps 60] [--models cnn lstm] [--windows 20 80]
                                       [--device cpu|cuda]

For each model and window, with the quick set and the quick experiment's settings
(``features=frame``, measurement noise drawn afresh at alpha = 1, batch 256, the training
config's optimizer: fused Adam, and gradient clipping), one training step is taken apart
and each part is timed on its own, ``steps`` times after a warm-up; the figures are medians
in milliseconds per step:

- gather: the batch of windows from the unfolded rows, with its noise drawn;
- features: the window in the measurement frame, normalised, cast to float32;
- forward + loss: the network and the loss, the features excluded;
- backward;
- optimiser: gradient-norm clipping, Adam's step, zeroing the gradients;
- Lightning: what a Lightning step (logging, callbacks, hooks) costs beyond the bare loop,
  the difference of the median step times of ``bench_train.py``'s two loops.

The evaluation on the test grid runs once per run, after training; its time is in every
run's MLflow metric ``eval_seconds``.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
import warnings

import torch
from bench_train import BATCH, SEED, bare, compose_cfg, lightning
from hydra.utils import instantiate
from omegaconf import OmegaConf

from lbo.learn.datamodule import WindowDataModule
from lbo.learn.draws import AlphaDraw
from lbo.models.features import window_features
from lbo.models.net import WindowNet
from lbo.sim.datasets import build, spec_from_cfg

PARTS = ("gather", "features", "forward + loss", "backward", "optimiser")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def profile(model: str, window: int, steps: int, device: torch.device) -> dict[str, float]:
    """Median milliseconds per step of each part of :data:`PARTS`."""
    cfg = compose_cfg(model, window)
    folder, _, _ = build(spec_from_cfg(cfg), progress=False)
    dm = WindowDataModule(folder, window, BATCH, seed=SEED, draw=AlphaDraw(),
                          sigma=tuple(cfg.noise.measurement_sigma), device=str(device))
    dm.setup("fit")
    norm = dm.normalisation("frame")
    spec = OmegaConf.to_container(cfg.model, resolve=True)
    net = WindowNet(spec.pop("name"), window, "frame", **spec).to(device)
    net.set_normalisation(**norm)
    opt = instantiate(cfg.optimizer)(params=net.parameters())
    ds, gen = dm.train_set, torch.Generator(device=device).manual_seed(SEED)
    order = torch.randperm(len(ds), generator=gen, device=device)
    times: dict[str, list[float]] = {p: [] for p in PARTS}
    for i in range(steps + 5):
        idx = order[i * BATCH:(i + 1) * BATCH]
        stamps = [time.perf_counter()]
        win, state, weight = (t.to(device) for t in ds.batch(idx, gen))
        _sync(device)
        stamps.append(time.perf_counter())
        x = ((window_features(win, "frame") - net.in_mean) / net.in_std).float()
        _sync(device)
        stamps.append(time.perf_counter())
        loss = net.loss(win, state, weight)
        _sync(device)
        stamps.append(time.perf_counter())
        loss.backward()
        _sync(device)
        stamps.append(time.perf_counter())
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        opt.zero_grad()
        _sync(device)
        stamps.append(time.perf_counter())
        del x
        if i >= 5:
            for part, a, b in zip(PARTS, stamps, stamps[1:], strict=False):
                times[part].append(b - a)
    out = {p: 1e3 * statistics.median(v) for p, v in times.items()}
    # forward + loss was timed with the features inside: take them out
    out["forward + loss"] = max(out["forward + loss"] - out["features"], 0.0)
    return out


def lightning_overhead(model: str, window: int, repeats: int = 3) -> float:
    """Median ms per step that Lightning adds to the bare loop (bench_train's two loops)."""
    cfg = compose_cfg(model, window)
    folder, _, _ = build(spec_from_cfg(cfg), progress=False)
    dm = WindowDataModule(folder, window, BATCH, seed=SEED)
    dm.setup("fit")
    norm = dm.normalisation(cfg.model.features)
    diffs = []
    for _ in range(repeats):
        b = bare(cfg, dm, norm, 5, 40)
        lt = lightning(cfg, dm, norm, 5, 40)
        diffs.append(statistics.median(lt.periods) - statistics.median(b.periods))
    return 1e3 * statistics.median(diffs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--models", nargs="+", default=["cnn", "lstm"])
    ap.add_argument("--windows", nargs="+", type=int, default=[20, 80])
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    device = torch.device(args.device)
    logging.getLogger("lightning.pytorch").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {device}, "
          f"batch {BATCH}; median ms per step of {args.steps} steps\n")
    head = "".join(f"{p:>16}" for p in (*PARTS, "Lightning", "total"))
    print(f"{'model':<6}{'N':>4}{head}")
    for m in args.models:
        for n in args.windows:
            parts = profile(m, n, args.steps, device)
            parts["Lightning"] = lightning_overhead(m, n) if device.type == "cpu" else 0.0
            total = sum(parts.values())
            cells = "".join(f"{v:>10.2f} ({100 * v / total:2.0f}%)" for v in parts.values())
            print(f"{m:<6}{n:>4}{cells}{total:>16.2f}", flush=True)


if __name__ == "__main__":
    main()
