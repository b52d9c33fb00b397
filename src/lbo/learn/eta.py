"""How long training will take: a few measured steps of each run, times its step count.

``make reproduce`` and ``make ablation`` print the expected time of their training before it
starts (:func:`plan`), for the chosen scale and device, and an ETA after every run
(:class:`Eta`).
"""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig


def steps_per_run(cfg: DictConfig, batches_per_epoch: int) -> int:
    """Training steps of a run that does not stop early: max_epochs x the batches it takes
    per epoch (``trainer.limit_train_batches``: a fraction, or a count)."""
    limit = cfg.trainer.get("limit_train_batches")
    if limit is None:
        per_epoch = batches_per_epoch
    elif isinstance(limit, float) and limit <= 1.0:
        per_epoch = max(int(limit * batches_per_epoch), 1)
    else:
        per_epoch = min(int(limit), batches_per_epoch)
    return int(cfg.trainer.max_epochs) * per_epoch


def measure(cfg: DictConfig, steps: int = 8, warmup: int = 3) -> dict[str, Any]:
    """Time ``steps`` training steps (after ``warmup``) of the run ``cfg`` on its device; a
    run of fewer steps than that is timed on as many steps as it has (half of them warm-up),
    so that its estimate never costs more than its training.

    Returns ``step_s`` (median seconds per step), ``steps`` (the run's step count),
    ``setup_s`` (reading the data set and building the model, once per run), ``eval_s`` (its
    validation in every epoch and its evaluation on the test set, from a forward pass timed;
    0 for a model trained carried), ``seconds`` (setup plus steps x step time plus eval_s: the
    expected training time, early stopping aside) and ``timed`` (the steps it took, warm-up
    included).
    """
    from lbo.learn.builders import build_net, data_device, datamodule, prepare_data
    from lbo.learn.sequence import from_batch, train_batch
    from lbo.models.carried import sequence_model

    begin = time.perf_counter()
    device = data_device(cfg)
    folder = prepare_data(cfg)[0]
    dm = datamodule(cfg, folder)
    net = build_net(cfg).to(device)
    net.set_normalisation(**dm.normalisation(net, cfg.model.normalisation))
    opt = instantiate(cfg.optimizer)(params=net.parameters())
    loader = dm.train_dataloader()
    # one carried model for every step: a compiled one compiles in the warm-up steps
    carried = sequence_model(net.net, bool(cfg.get("compile"))) \
        if cfg.get("tbptt") is not None else None
    setup_s = time.perf_counter() - begin
    n = steps_per_run(cfg, len(loader))
    if n < warmup + steps:
        warmup = n // 2
        steps = max(n - warmup, 1)
    periods = []
    def step(loss: torch.Tensor) -> None:
        opt.zero_grad()
        loss.backward()
        opt.step()

    for i, batch in enumerate(loader):
        start = time.perf_counter()
        if carried is None:
            step(net.loss(*batch))
        else:  # trained carried: a step per chunk
            m, u, z, weight = from_batch(batch, next(net.parameters()).dtype)
            train_batch(carried, m, u, z, int(cfg.tbptt), step, weight,
                        float(cfg.get("nll") or 0.0))
        if device == "cuda":
            torch.cuda.synchronize()
        if i >= warmup:
            periods.append(time.perf_counter() - start)
        if len(periods) == steps:
            break
    step_s = statistics.median(periods)
    eval_s = _forward_s(cfg, net, dm, folder, str(device)) if carried is None else 0.0
    return {"step_s": step_s, "steps": n, "setup_s": setup_s, "eval_s": eval_s,
            "seconds": setup_s + step_s * n + eval_s, "timed": warmup + len(periods)}


def _forward_s(cfg: DictConfig, net: Any, dm: Any, folder: Path, device: str) -> float:
    """Seconds of the forward passes a run makes besides its steps, each timed: every epoch's
    validation (one batch of its loader, times its batches) and the final evaluation on the
    test set (:func:`lbo.scoring.grid.predict` on its first few trajectories and on twice as
    many, carried on in a line to all of them: the recursive form runs them together)."""
    from lbo.scoring.grid import load_test, predict

    def timed(run: Any) -> float:
        start = time.perf_counter()
        run()
        if device.startswith("cuda"):  # its kernels run on after the call returns
            torch.cuda.synchronize()
        return time.perf_counter() - start

    loader = dm.val_dataloader()
    batch = next(iter(loader))
    net.eval()
    with torch.no_grad():  # once: the training steps timed before warmed the model up
        one = timed(lambda: net.loss(*batch))
    val_s = one * len(loader) * int(cfg.trainer.max_epochs)
    test = folder / "test.parquet"
    if not test.is_file():  # a user's logs: scored file by file, not timed here
        return val_s
    arr = load_test(test)
    g = len(arr.alpha)
    k = min(4, g)
    first = timed(lambda: predict(net, arr.take(np.arange(k)), device=device))
    if g == k:
        return val_s + first
    twice = timed(lambda: predict(net, arr.take(np.arange(min(2 * k, g))), device=device))
    per = max(twice - first, 0.0) / (min(2 * k, g) - k)
    return val_s + first + per * (g - k)


def duration(seconds: float) -> str:
    """``95`` -> ``1 min 35 s``; ``7300`` -> ``2 h 2 min``."""
    seconds = max(float(seconds), 0.0)
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 3600:
        return f"{int(seconds // 60)} min {int(seconds % 60)} s"
    return f"{int(seconds // 3600)} h {math.ceil(seconds % 3600 / 60)} min"


def more(count: int, unit: str, each_s: float, basis: str) -> str:
    """The line that says how long ``count`` more ``unit``s will take at ``each_s`` seconds
    each, the time measured on ``basis`` (the first trial, epoch 0)."""
    return (f"estimate: {count} more {unit}{'s' if count > 1 else ''} x {each_s:.1f} s "
            f"({basis}): about {duration(count * each_s)}")


TIMING_SHARE = 0.1
"""The most that timing the runs of a plan may cost, as a share of what the runs it timed
would train. A run is timed in a few seconds: every run of a quick or paper study (minutes
to hours each) is, while a smoke study (seconds each) times its first run only. At a half,
the rerun of ``tests/test_reproduce.py``'s killed smoke study timed runs for about 6 s beside
its 28 s of training (py-spy, 2026-12-01)."""


def plan(runs: list[tuple[str, DictConfig]], parallel: int = 1, scale: str = "") -> Eta:
    """Measure a few steps of every run of ``runs`` (``(name, training config)`` pairs) that is
    still to train, print one line each and the expected total, and return their :class:`Eta`.

    A run that finished before (same config hash) is expected to take nothing; ``parallel``
    runs train at once (the total is divided by it); ``scale`` is named in the total line.
    Once measuring has taken more than :data:`TIMING_SHARE` of what the runs measured would
    train (a smoke study, where timing a run costs about what training it does), the runs
    left are not measured: each is expected to take the mean of those measured.
    """
    from lbo.learn.builders import data_device
    from lbo.learn.identity import config_hash
    from lbo.learn.resume import finished_run

    estimates: list[float] = []
    measured: list[float] = []
    guessed = 0
    begin = time.perf_counter()
    for name, cfg in runs:
        if finished_run(cfg, config_hash(cfg), clean=False) is not None:
            estimates.append(0.0)
            continue
        if measured and time.perf_counter() - begin > TIMING_SHARE * sum(measured):
            estimates.append(sum(measured) / len(measured))
            guessed += 1
            continue
        m = measure(cfg)
        estimates.append(m["seconds"])
        measured.append(m["seconds"])
        print(f"    {name}: {m['steps']} steps x {1e3 * m['step_s']:.1f} ms + "
              f"{m['setup_s']:.1f} s setup + {m['eval_s']:.1f} s validation and test = "
              f"{duration(m['seconds'])}", flush=True)
    if guessed:
        print(f"    the other {guessed}: about {duration(sum(measured) / len(measured))} each, "
              f"as the {len(measured)} measured (measuring them would cost about what training "
              "them does)", flush=True)
    total = sum(estimates) / max(min(parallel, len(runs)), 1)
    at = f" at scale {scale}" if scale else ""
    print(f"    expected: about {duration(total)} of training{at} on {data_device(runs[0][1])} "
          f"(measured steps x steps per run, and forward passes for validation and the test "
          f"set, timed in {time.perf_counter() - begin:.0f} s; early stopping can only shorten "
          "it)", flush=True)
    return Eta(estimates)


class Eta:
    """Remaining time of a list of runs, from their estimates scaled by how the finished ones
    compared with theirs."""

    def __init__(self, estimates: list[float]) -> None:
        self.estimates = list(estimates)
        self.done_estimated = 0.0
        self.done_actual = 0.0

    def skipped(self, i: int) -> float:
        """Run ``i`` was reused, not trained; returns the seconds expected for the runs left."""
        self.estimates[i] = 0.0
        return self.left()

    def left(self) -> float:
        scale = self.done_actual / self.done_estimated if self.done_estimated > 0 else 1.0
        return sum(self.estimates) * scale

    def finished(self, i: int, seconds: float) -> float:
        """Run ``i`` took ``seconds``; returns the seconds expected for the runs left."""
        self.done_estimated += self.estimates[i]
        self.done_actual += seconds
        self.estimates[i] = 0.0
        return self.left()
