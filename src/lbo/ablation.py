"""`make ablation`: why the paper's networks degrade gracefully with noise and ours do not.

    python -m lbo.ablation [scale=quick] [sweeps=[...]]

Trains (or reuses, ``resume=true``) every variant of ``sweeps``, after printing how long that
will take (a few steps of each run measured); each entry is a sweep of ``lbo.train`` written
as on its command line (``features=absolute,relative`` crosses the values). Then it fits the
paper's EKF (our EKF with its process noise scaled, R at alpha = 1) and writes to
``report_dir``:

- ``ekf_fit.csv``: every EKF setting tried, closest to the paper's EKF first;
- ``scores.csv``: per variant the seed-mean score rows, with our EKF, the oracle, the closest
  EKF setting (``ekf_paper_fit``) and the paper's published points (``paper_*``);
- ``ablation.csv`` and ``ablation.md``: one row per variant, RMSE at alpha 1, 3 and 6, the
  growth of the NRMSE from alpha 1 to 6, the crossovers, the distance to the paper's tables;
- ``ablation.png``: the NRMSE curves, CNN and LSTM side by side.
"""

from __future__ import annotations

import itertools
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from hydra import compose
from omegaconf import DictConfig

from lbo.core import plots
from lbo.core.atomic import atomic_path, write_text
from lbo.core.cli import entry, respell
from lbo.core.errors import LboError
from lbo.core.paths import store_overrides
from lbo.tracking.runs import check_store, run_artifact

FACTORS = ("features", "train_noise", "activation", "normalisation", "epochs")
"""What tells the variants apart (the seed does not: seeds of a variant are averaged)."""


def expand(sweep: str) -> list[list[str]]:
    """Every override list of one command-line sweep: ``"a=1,2 b=x"`` -> ``[[a=1, b=x],
    [a=2, b=x]]``. A value in brackets (a list) is kept whole."""
    choices = []
    for token in sweep.split():
        key, sep, values = token.partition("=")
        if not sep or not key or not values:
            raise LboError(f"sweeps: expected key=value[,value...] tokens, got {token!r} in "
                           f"{sweep!r}")
        parts = [values] if values.startswith("[") else values.split(",")
        choices.append([f"{key}={v}" for v in parts])
    return [list(c) for c in itertools.product(*choices)]


def factors(cfg: DictConfig) -> dict[str, Any]:
    """The variant a training config is: model, window and :data:`FACTORS`, and its seed."""
    source = cfg.train_noise.source
    return {"model": cfg.model.name, "window": int(cfg.model.window),
            "features": cfg.model.features,
            "train_noise": "stored" if source == "stored" else "fresh",
            "activation": cfg.model.get("activation", "-"),
            "normalisation": cfg.model.normalisation, "epochs": epochs(cfg),
            "seed": int(cfg.seed)}


def epochs(cfg: DictConfig) -> float:
    """The training length in passes over the training windows: max_epochs times the share of
    each epoch trained (``limit_train_batches`` as a fraction; a batch count reads as 1)."""
    limit = cfg.trainer.get("limit_train_batches")
    share = float(limit) if isinstance(limit, float) and limit <= 1.0 else 1.0
    return float(cfg.trainer.max_epochs) * share


def label(f: dict[str, Any], base_epochs: float | None = None) -> str:
    """``cnn-N60 frame fresh centred_sigmoid standard``: a variant's name in the tables; its
    training length is named when it is not ``base_epochs``, the scale's own."""
    parts = [f"{f['model']}-N{f['window']}", f["features"], f["train_noise"]]
    if f["activation"] != "-":
        parts.append(f["activation"])
    parts.append(f["normalisation"])
    if base_epochs is not None and f["epochs"] != base_epochs:
        parts.append(f"{f['epochs']:g} epoch{'' if f['epochs'] == 1 else 's'}")
    return " ".join(parts)


def jobs(cfg: DictConfig) -> list[list[str]]:
    """The training overrides of every run of the ablation, in order, duplicates once."""
    out: dict[str, list[str]] = {}
    for sweep in cfg.sweeps:
        for combo in expand(sweep):
            # each run's bars hidden (the command says each run's result as it ends); each
            # run logs to the store the tables are read from
            out.setdefault(" ".join(combo), respell([
                f"experiment={cfg.scale}", *combo, "resume=true",
                "callbacks.progress_bar.refresh_rate=0",
                *store_overrides(cfg.tracking_uri), *cfg.overrides]))
    return list(out.values())


def ablation(cfg: DictConfig) -> Path:
    """Train or reuse the variants, fit the paper's EKF, write the tables and the figure."""
    from lbo.learn.builders import prepare_data
    from lbo.learn.eta import duration, plan
    from lbo.scoring import paper_protocol as pp
    from lbo.scoring.grid import load_test, reference, score
    from lbo.sim.noise import Noise
    from lbo.sim.vehicle import Vehicle
    from lbo.train import check, train

    check_store(cfg.tracking_uri, "tracking_uri")
    out = Path(cfg.report_dir)
    base = epochs(compose("train", [f"experiment={cfg.scale}"]))
    configs = []
    for overrides in jobs(cfg):
        c = compose("train", overrides)
        f = factors(c)
        key = label(f, base)
        c.output_dir = str(out / "runs" / f"{key.replace(' ', '_')}_seed{f['seed']}")
        check(c)  # every run's settings before the first one trains
        configs.append((c, f, key))
    print(f"==> {len(configs)} runs to train or reuse", flush=True)
    eta = plan([(f"{key}, seed {f['seed']}", c) for c, f, key in configs], scale=cfg.scale)
    per_variant: dict[str, list[pd.DataFrame]] = {}
    variants: dict[str, dict[str, Any]] = {}
    for i, (c, f, key) in enumerate(configs, 1):
        print(f"==> [{i}/{len(configs)}] {key}, seed {f['seed']}", flush=True)
        start = time.perf_counter()
        run = train(c)
        seconds = time.perf_counter() - start
        left = eta.skipped(i - 1) if run.get("reused") else eta.finished(i - 1, seconds)
        print(f"    {'reused' if run.get('reused') else f'trained in {seconds:.0f} s'}: MLflow "
              f"run {run['run_id']}" + (f", ETA {duration(left)}" if i < len(configs) else ""),
              flush=True)
        t = pd.read_csv(run_artifact(run, "evaluation.csv", cfg.tracking_uri))
        per_variant.setdefault(key, []).append(t.assign(observer=t["observer"].replace(
            run["name"], key)))
        variants[key] = {"label": key, **{k: v for k, v in f.items() if k != "seed"}}
    first = configs[0][0]
    folder, _ = prepare_data(first)
    arr = load_test(Path(folder) / "test.parquet")
    vehicle, noise = Vehicle.from_cfg(first.vehicle), Noise.from_cfg(first.noise)
    print("==> the paper's EKF: our EKF with its process noise scaled, R at alpha = 1",
          flush=True)
    fit = pp.fit_paper_ekf(arr, vehicle, noise)
    best = fit.iloc[0]
    ref = reference(arr, vehicle, noise)  # the E_ref every run's table was scored with
    firsts = next(iter(per_variant.values()))[0]
    classical = firsts[firsts["observer"].isin(["ekf", "oracle"])]
    fitted = score(pp.PAPER_FIT, pp.run_scaled_ekf(arr, vehicle, noise, best["q_position"],
                                                   best["q_heading"]), arr, ref)
    table = pd.concat([*(pp.mean_over_seeds(ts, k, k) for k, ts in per_variant.items()),
                       classical, fitted, pp.paper_rows(ref)], ignore_index=True)
    summary = pp.variant_summary(table, pd.DataFrame(list(variants.values())))
    files = {"ekf_fit.csv": fit, "scores.csv": table, "ablation.csv": summary}
    for fname, frame in files.items():
        with atomic_path(out / fname) as tmp:
            frame.to_csv(tmp, index=False)
    panels = {f"{m.upper()}": [*[k for k, v in variants.items() if v["model"] == m], "ekf",
                               "oracle", pp.PAPER_FIT]
              for m in dict.fromkeys(v["model"] for v in variants.values())}
    plots.save(plots.nrmse_panels(table, panels, "trained at alpha = 1: variants of the paper's "
                                  "protocol (seed means)",
                                  points={m.upper(): [f"paper_{m}", "paper_ekf"]
                                          for m in ("cnn", "lstm")},
                                  styles={pp.PAPER_FIT: {"color": "black", "ls": "--",
                                                         "lw": 1.6}}),
               out / "ablation.png")
    md = markdown(summary, fit)
    write_text(out / "ablation.md", md)
    print(md)
    print(f"report: {out / 'ablation.md'}")
    return out


def _cell(v: Any, digits: int = 2) -> str:
    if isinstance(v, float):
        return "never" if np.isnan(v) else f"{v:.{digits}f}"
    return str(v)


def markdown(summary: pd.DataFrame, fit: pd.DataFrame) -> str:
    """ablation.md: the variants' table and the EKF fit."""
    from lbo.scoring.paper_protocol import FIT_TOLERANCE, PAPER_FIT, SHAPE_TOLERANCE, paper_rmse

    cols = ["label", "seeds", "x_1", "y_1", "psi_1", "x_3", "y_3", "psi_3", "x_6", "y_6",
            "psi_6", "growth", "crossover_ekf", f"crossover_{PAPER_FIT}", "paper_alpha1",
            "paper_alpha6"]
    lines = ["# Ablation: the paper's protocol, variant by variant", "",
             "RMSE x, y (m) and psi (mrad) at alpha 1, 3 and 6 (seed means); growth: NRMSE at "
             "6 over NRMSE at 1; crossover: the alpha from which the variant stays below that "
             f"EKF; paper_alpha1/6: the largest factor between its RMSE and the paper's "
             f"(Table I / II), {SHAPE_TOLERANCE:g} or less reproduces it.", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in summary.to_dict("records"):
        lines.append("| " + " | ".join(_cell(r.get(c, np.nan), 1 if c.startswith("psi") else 2)
                                      for c in cols) + " |")
    best = fit.iloc[0]
    verdict = "fits" if best["deviation"] <= FIT_TOLERANCE else "does not fit"
    lines += ["", "## The paper's EKF", "",
              f"Closest setting: process sigmas x {best['q_position']:g} (position) and "
              f"x {best['q_heading']:g} (heading), R at alpha = 1: largest deviation from the "
              f"paper's EKF {best['deviation']:.0%}, so it {verdict} within "
              f"{FIT_TOLERANCE:.0%}.", "",
              "| q_position | q_heading | x_1 | y_1 | psi_1 | x_6 | y_6 | psi_6 | growth_x | "
              "growth_y | growth_psi | deviation |", "|" + "---|" * 12]
    for r in fit.head(8).to_dict("records"):
        lines.append("| " + " | ".join(_cell(r[c]) for c in (
            "q_position", "q_heading", "x_1", "y_1", "psi_1", "x_6", "y_6", "psi_6",
            "growth_x", "growth_y", "growth_psi", "deviation")) + " |")
    (x1, y1, p1), (x6, y6, p6) = paper_rmse("ekf")
    lines += ["", f"The paper's EKF: {x1:g} m, {y1:g} m, {p1 * 1e3:g} mrad at alpha 1; {x6:g} m, "
              f"{y6:g} m, {p6 * 1e3:g} mrad at alpha 6 (growth {x6 / x1:.1f}, {y6 / y1:.1f}, "
              f"{p6 / p1:.1f}).", ""]
    return "\n".join(lines)


def check_ablation(cfg: DictConfig) -> None:
    """Reject an empty or malformed sweep list before anything trains."""
    if not cfg.sweeps:
        raise LboError("sweeps: expected a list of lbo.train sweeps, got none")
    jobs(cfg)


def _main(cfg: DictConfig) -> Path:
    check_ablation(cfg)
    return ablation(cfg)


main = entry("ablation", _main)


if __name__ == "__main__":
    sys.exit(main())
