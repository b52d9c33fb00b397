"""Every learned observer on three data sets, under one budget: the comparison table.

    python benchmarks/learned_table.py [--cells paper/cnn,dynamic/split_kalmannet] [--out DIR]
                                       [--reuse robust/kalmannet=outputs/...] [-- OVERRIDES]

The observers (rows): the paper's CNN and LSTM (N=80), the robust observer (the learned-noise
window EKF, ``model=filternet``), the car-that-slips observer (the same with the learned
single-track body and drift states, ``experiment=dynamic``'s model), KalmanNet and
Split-KalmanNet (around the kinematic bicycle, and around the single-track body on the car
that slips), and Split-KalmanNet trained carried (``tbptt``, as its authors train it; it then
runs carried). The data sets (protocols):

- ``paper``: the paper's protocol at the quick scale: ``data=quick``, trained at alpha = 1
  (``train_noise=paper``), scored over alpha 0..6; every window N=80;
- ``robust``: ``experiment=robust``: alpha drawn on [0, 6.5] per window, fixes dropped to 50,
  10, 5 or 1 Hz; the filters N=400, the CNN and LSTM N=80;
- ``dynamic``: the car that slips, ``data=dynamic`` with ``experiment=dynamic``'s noise
  (the CNN and LSTM as ``experiment=dynamic_blackbox``); the filters N=400.

Every cell trains on the same budget, the robust observer's: 4 epochs of 100 batches of 256
windows (102,400 windows), a cosine schedule, fresh noise per window. Each cell is one
``python -m lbo.train`` run in ``<out>/<data set>-<observer>/`` (tracked in MLflow as any
run); a cell whose run folder already holds ``evaluation.csv`` is read, not trained again,
so a killed table goes on where it stopped. The table (``<out>/table.md``, ``cells.csv``)
gives each cell's NRMSE at alpha 1, 3 and 6, its ratio to the oracle there (on ``dynamic``,
to ``oracle_dynamic``, the EKF told the car), its parameters and its training time (the
MLflow run's, evaluation included). Overrides after ``--`` go to every run (the smoke test's
scale).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from lbo.core.atomic import write_text

BUDGET = ("batch_size=256", "trainer.max_epochs=4", "++trainer.limit_train_batches=100",
          "lr_schedule=cosine", "callbacks.early_stopping.patience=4")
"""The budget of every cell: the robust observer's (``experiment=robust``)."""
PROTOCOLS = {
    "paper": ("data=quick", "train_noise=paper", "features=frame", "optimizer.lr=0.003"),
    "robust": ("experiment=robust",),
    "dynamic": ("experiment=dynamic",),
}
"""Each data set's overrides, before the observer's."""
SLIPS = ("model=filternet", "model.body=single_track", "+model.body_lr=3.0",
         "+model.drift=true", "optimizer.lr=0.005")
"""The car-that-slips observer (``experiment=dynamic``'s model) where the data set does not
set it."""
OBSERVERS = {
    "cnn": {"paper": ("model=cnn", "window=80"),
            "robust": ("model=cnn", "window=80"),
            "dynamic": ("experiment=dynamic_blackbox", "model=cnn")},
    "lstm": {"paper": ("model=lstm", "window=80"),
             "robust": ("model=lstm", "window=80"),
             "dynamic": ("experiment=dynamic_blackbox", "model=lstm")},
    "robust": {"paper": ("model=filternet", "window=80"),
               "robust": (),
               "dynamic": ("model.body=kinematic", "model.body_lr=1.0", "model.drift=false",
                           "optimizer.lr=0.003")},
    "slips": {"paper": (*SLIPS, "window=80"),
              "robust": SLIPS,
              "dynamic": ()},
    "kalmannet": {"paper": ("model=kalmannet", "window=80"),
                  "robust": ("model=kalmannet",),
                  "dynamic": ("model=kalmannet", "~model.drift")},
    "split_kalmannet": {"paper": ("model=split_kalmannet", "window=80"),
                        "robust": ("model=split_kalmannet",),
                        "dynamic": ("model=split_kalmannet", "~model.drift")},
    # trained carried, as its authors train it: sequences cut into chunks of 100 steps, as
    # many sequence steps as the budget's windows hold (102,400 x 400 = 41 million)
    "split_kalmannet_carried": {
        "paper": ("model=split_kalmannet", "window=80", "tbptt=20"),
        "robust": ("model=split_kalmannet", "window=1000", "tbptt=100", "batch_size=100"),
        "dynamic": ("model=split_kalmannet", "~model.drift", "tbptt=100",
                    "sequence_length=800", "batch_size=128")},
}
"""Each observer's overrides on each data set (after the data set's)."""
LABELS = {"cnn": "CNN (N=80)", "lstm": "LSTM (N=80)", "robust": "robust observer",
          "slips": "car-that-slips observer", "kalmannet": "KalmanNet",
          "split_kalmannet": "Split-KalmanNet",
          "split_kalmannet_carried": "Split-KalmanNet, trained carried (`tbptt=100`)"}
ALPHAS = (1.0, 3.0, 6.0)


@dataclass(frozen=True)
class Cell:
    """One observer on one data set, and its run folder."""

    data: str
    observer: str
    folder: Path

    @property
    def overrides(self) -> list[str]:
        dynamic_blackbox = self.data == "dynamic" and self.observer in ("cnn", "lstm")
        protocol = () if dynamic_blackbox else PROTOCOLS[self.data]
        own = OBSERVERS[self.observer][self.data]
        keys = {o.split("=")[0].lstrip("+~") for o in own}
        # the budget's settings, but those the observer sets (a batch of sequences)
        budget = [b for b in BUDGET if b.split("=")[0].lstrip("+~") not in keys]
        return [*protocol, *own, *budget]


def cells(names: str | None, out: Path, reuse: dict[str, Path]) -> list[Cell]:
    """The cells named ``data/observer`` (all when None), in the table's order."""
    every = [f"{d}/{o}" for d in PROTOCOLS for o in OBSERVERS]
    chosen = every if names is None else [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in chosen + list(reuse) if n not in every]
    if unknown:
        sys.exit(f"error: --cells: unknown cell(s) {', '.join(unknown)}; expected "
                 f"<data set>/<observer> of {', '.join(every)}")
    return [Cell(*n.split("/"), reuse.get(n, out / n.replace("/", "-"))) for n in chosen]


def train(cell: Cell, extra: list[str]) -> None:
    """Train and score one cell in its folder (:func:`main` skips a finished one)."""
    cmd = [sys.executable, "-m", "lbo.train", *cell.overrides, *extra,
           f"hydra.run.dir={cell.folder}"]
    print(f"[{time.strftime('%H:%M:%S')}] {cell.data}/{cell.observer}: {' '.join(cmd[3:])}",
          flush=True)
    res = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if res.returncode != 0:
        tail = res.stderr.strip().splitlines()[-1:] or ["(no message)"]
        raise SystemExit(f"error: {cell.data}/{cell.observer} failed (exit "
                         f"{res.returncode}): {tail[0]}")


def measure(cell: Cell) -> dict:
    """The cell's row: NRMSE and the ratio to its oracle at :data:`ALPHAS`, its parameters
    and its training time (s), from its run folder and its MLflow run."""
    import mlflow
    import torch

    from lbo import Observer
    from lbo.core.paths import tracking_uri
    from lbo.learn.resume import IDENTITY_KEY

    table = pd.read_csv(cell.folder / "evaluation.csv")
    nr = table.pivot(index="alpha", columns="observer", values="nrmse")
    learned = [o for o in nr.columns if "-N" in o]
    if len(learned) != 1:
        raise SystemExit(f"error: {cell.folder}/evaluation.csv: expected one learned "
                         f"observer, got {learned}")
    oracle = "oracle_dynamic" if "oracle_dynamic" in nr.columns else "oracle"
    ckpt = cell.folder / "checkpoints" / "best.ckpt"
    net = Observer.load(ckpt).net
    params = sum(p.numel() for p in net.parameters())
    run_id = torch.load(ckpt, map_location="cpu", weights_only=True)[IDENTITY_KEY]["run_id"]
    info = mlflow.MlflowClient(tracking_uri()).get_run(run_id).info
    row = {"data": cell.data, "observer": cell.observer, "run": learned[0],
           "oracle": oracle, "parameters": params,
           "seconds": (info.end_time - info.start_time) / 1000.0, "folder": str(cell.folder)}
    for a in ALPHAS:
        for who, key in ((learned[0], ""), ("ekf", "ekf_")):  # the EKF: the reference row
            row[f"{key}nrmse_{a:g}"] = float(nr.loc[a, who])
            row[f"{key}ratio_{a:g}"] = float(nr.loc[a, who] / nr.loc[a, oracle])
    return row


def markdown(rows: pd.DataFrame) -> str:
    """The table: one line per cell, grouped by data set, each data set's first line the EKF
    told alpha = 1 (R at alpha = 1), for reference."""
    head = ("| data set | observer | NRMSE a=1 | a=3 | a=6 | / oracle a=1 | a=3 | a=6 | "
            "parameters | training |")
    lines = [head, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def line(r, label: str, key: str, tail: str) -> str:
        oracle = " (dyn.)" if r.oracle == "oracle_dynamic" else ""
        return (f"| {r.data} | {label} | "
                + " | ".join(f"{getattr(r, f'{key}nrmse_{a:g}'):.3f}" for a in ALPHAS) + " | "
                + " | ".join(f"{getattr(r, f'{key}ratio_{a:g}'):.2f}{oracle if a == 1 else ''}"
                             for a in ALPHAS) + f" | {tail} |")

    shown: set[str] = set()
    for r in rows.itertuples():
        if r.data not in shown:
            shown.add(r.data)
            lines.append(line(r, "EKF, R at alpha = 1", "ekf_", "| "))
        m, s = divmod(round(r.seconds), 60)
        lines.append(line(r, LABELS[r.observer], "",
                          f"{r.parameters / 1000:.1f} K | {m} min {s:02d} s"))
    return "\n".join(lines) + "\n"


def main() -> None:
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", help="data/observer,... (default: all 21)")
    ap.add_argument("--out", type=Path, default=Path("outputs/learned_table"))
    ap.add_argument("--reuse", action="append", default=[],
                    help="data/observer=<run folder>: read that run instead of training")
    args = ap.parse_args(argv)
    reuse = dict(r.split("=", 1) for r in args.reuse)
    chosen = cells(args.cells, args.out, {k: Path(v) for k, v in reuse.items()})
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for cell in chosen:
        if not (cell.folder / "evaluation.csv").is_file():
            train(cell, extra)
        rows.append(measure(cell))
        frame = pd.DataFrame(rows)  # each finished cell kept at once, never half-written
        write_text(args.out / "cells.csv", frame.to_csv(index=False))
        write_text(args.out / "table.md", markdown(frame))
    print(markdown(pd.DataFrame(rows)), end="")


if __name__ == "__main__":
    main()
