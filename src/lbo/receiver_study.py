"""`python -m lbo.receiver_study`: the observers on simulated single-antenna logs, beside an oracle.

    python -m lbo.receiver_study [alphas=[1,3,6]] [drives=3] [learn.epochs=12]
                                 [output_dir=reports/receiver_study]

Simulates ``drives`` logs at each alpha (``python -m lbo.simulate receiver=single_antenna``:
fixes without heading at 1 Hz, their reported accuracy, a GNSS velocity and a gyro with a
bias that walks; alpha scales the receiver's errors) and scores on each, from its first
course over ground on (:func:`lbo.scoring.receiver.score`):

- the raw fixes; every classical observer with the receiver's channels; the EKF without them
  and smoothed; each learned observer of ``nets`` with the receiver's channels;
- the gyro EKF with its noise learned once on simulated drives spread over
  ``learn.alpha_range`` (:mod:`lbo.learn.gyro_fit`; one noise for every alpha, never told
  it: the receiver's reported accuracy carries the scale);
- two oracle gyro EKFs (:func:`lbo.scoring.receiver.oracle_gyro`), both told the true noise:
  one also told the gyro's true bias, which every row is measured against (``vs_oracle``:
  the quadratic mean over x, y and psi of the RMSE ratios), and one told only the bias's
  statistics, which must learn its value from the log as every causal filter here must
  (``vs_noise_oracle``);
- two more told also the fixes' drift (as two states) and the channels' latency: the one
  told the bias is the reference of ``vs_full_oracle``, the one that estimates it the best
  causal filter we know for these logs.

Writes ``results.csv`` (one row per alpha and estimator, RMSE pooled over the drives),
``results.md``, ``ratios.png`` (``vs_oracle`` against alpha) and ``gyro_noise.json`` (with
its ``_history.csv``), and prints the table.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from lbo.core.atomic import atomic_path
from lbo.core.checks import integer, number, require
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.gyro_noise import FixDrift, GyroNoise
from lbo.logs.io import check_output_path, write_table
from lbo.scoring import receiver as scoring
from lbo.sim.noise import check_alpha

__all__ = ["LEARNED", "RATIOS", "main", "plot", "receiver_study"]

LEARNED = "gyro, noise learned on simulated drives over alpha"
"""The row of the gyro EKF whose noise was learned once for every alpha."""
RATIOS = {"vs_oracle": scoring.ORACLE, "vs_noise_oracle": scoring.NOISE_ORACLE,
          "vs_full_oracle": scoring.FULL_ORACLE}
"""The ratio columns of the results, each to its oracle's row."""


def _drive(base: DictConfig, alpha: float, seed: int) -> pd.DataFrame:
    """One simulated single-antenna log at ``alpha`` (with truth and the gyro's bias);
    ``base``: the study's config, resolved and out of struct mode (:func:`_resolved`)."""
    from lbo.simulate import simulate

    one = OmegaConf.create(base)  # a copy: each drive sets its own alpha and seed
    one.alpha, one.seed = float(alpha), int(seed)
    return simulate(one)


def _resolved(cfg: DictConfig) -> DictConfig:
    """The config resolved once, out of struct mode, for :func:`_drive` to copy."""
    # a mapping's container is a dict, and a dict's config a DictConfig
    return cast(DictConfig, OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))


def _settings(cfg: DictConfig) -> dict[str, Any]:
    """The study's numbers, each checked in one line."""
    from lbo.learn.gyro_fit import Settings  # torch: only once the study runs

    alphas = [check_alpha(a, "alphas") for a in cfg.alphas]
    require(len(alphas) > 0, "alphas", "a list of noise scales >= 0", list(cfg.alphas))
    low, high = (number(a, "learn.alpha_range", low=0.0, form="[low, high], each >= 0")
                 for a in cfg.learn.alpha_range)
    require(high >= low, "learn.alpha_range", "[low, high] with high >= low",
            list(cfg.learn.alpha_range))
    for name in cfg.observers:
        classical.check(str(name), "observers")
    return {"alphas": alphas, "drives": integer(cfg.drives, "drives", 1),
            "seed": integer(cfg.seed, "seed", 0),
            "learn": Settings.from_cfg(cfg.learn),
            "learn_drives": integer(cfg.learn.drives, "learn.drives", 2),
            "range": (low, high)}


def receiver_study(cfg: DictConfig) -> dict[str, Any]:
    """Score every observer on simulated single-antenna logs at each alpha (see the module)."""
    from lbo.learn import gyro_fit
    from lbo.sim.noise import Noise
    from lbo.sim.receiver import SIGMA_FLOOR, ReceiverSpec
    from lbo.sim.vehicle import Vehicle

    s = _settings(cfg)
    if cfg.get("receiver") is None:
        raise LboError("receiver: expected a receiver to simulate (receiver=single_antenna)")
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    spec = ReceiverSpec.from_cfg(cfg.receiver, vehicle.dt)
    nets = scoring.load_nets(cfg.get("nets"))
    out = Path(str(cfg.output_dir))
    check_output_path(out / "results.csv")
    out.mkdir(parents=True, exist_ok=True)
    base = _resolved(cfg)
    learned: dict[str, GyroNoise] = {}
    if s["learn"].epochs:
        n = s["learn_drives"]
        span: tuple[float, float] = s["range"]
        # each drive its own alpha, the train and the validation drives each spread over
        # the whole range
        levels = [*np.linspace(*span, n), *np.linspace(*span, max(1, n // 2))]
        logs = [_drive(base, a, s["seed"] + j) for j, a in enumerate(levels)]
        R = gyro_fit.fix_cov(noise)
        learned[LEARNED] = gyro_fit.fit_and_write(
            out, "gyro_noise", logs[:n], logs[n:], vehicle, R,
            s["learn"].start(noise.Q),
            f"on {n} simulated drives at alpha {s['range'][0]:g} to {s['range'][1]:g}",
            **s["learn"].kwargs(vehicle.dt))
    tables = []
    for i, alpha in enumerate(s["alphas"]):
        per_drive = []
        for j in range(s["drives"]):
            log = _drive(base, alpha, s["seed"] + 100 * (i + 1) + j)
            process = float(np.sqrt(np.prod(noise.process_sigma[:2])))
            told = (log, vehicle, max(alpha * spec.position.sigma, SIGMA_FLOOR), process,
                    spec.gyro.sigma)
            # told the drift (its white part the fix's R) and the latency too
            full = (log, vehicle, max(alpha * spec.position.white, SIGMA_FLOOR), process,
                    spec.gyro.sigma)
            timing: dict[str, Any] = {  # oracle_gyro's drift and latency
                "drift": FixDrift(max(alpha * spec.position.drift, SIGMA_FLOOR),
                                  spec.position.tau),
                "latency": (spec.position.latency, spec.velocity.latency)}
            statistics = (spec.gyro_bias, spec.gyro_walk)
            oracles = {scoring.FULL_NOISE_ORACLE: scoring.oracle_gyro(
                           *full, bias=statistics, **timing),
                       scoring.FULL_ORACLE: scoring.oracle_gyro(*full, **timing),
                       scoring.NOISE_ORACLE: scoring.oracle_gyro(*told, bias=statistics),
                       scoring.ORACLE: scoring.oracle_gyro(*told)}
            table, _ = scoring.score(log, list(cfg.observers), vehicle, noise, learned, oracles,
                                     nets=nets)
            per_drive.append(table)
        table = scoring.pool(per_drive)
        table.insert(0, "alpha", float(alpha))
        for column, label in RATIOS.items():
            table[column] = scoring.ratio_to(table, label)
        tables.append(table)
        print(f"alpha {alpha:g} ({s['drives']} drives): RMSE pooled over the drives")
        print(scoring.markdown(table, *RATIOS), end="")
    results = pd.concat(tables, ignore_index=True)
    write_table(results, out / "results.csv")
    with atomic_path(out / "results.md") as tmp:
        Path(tmp).write_text("".join(f"\n## alpha = {t['alpha'].iloc[0]:g}\n\n"
                                     + scoring.markdown(t, *RATIOS) for t in tables))
    plot(results, out / "ratios.png")
    print(f"written: {out / 'results.md'}, {out / 'ratios.png'}")
    return {"table": results, "learned": learned}


def plot(results: pd.DataFrame, path: Path) -> Path:
    """``vs_oracle`` against alpha, one curve per estimator of ``results`` (as
    ``results.csv``), the EKF without the receiver's channels left out (off the scale)."""
    from lbo.core import plots

    curves = results.rename(columns={"estimator": "observer", "vs_oracle": "nrmse"})
    shown = [e for e in dict.fromkeys(curves["observer"]) if e != scoring.BLIND]
    # the oracles in greys, dashed where they must learn the bias: references, not peers
    oracles = {scoring.ORACLE: {"color": "black"},
               scoring.NOISE_ORACLE: {"color": "black", "ls": "--"},
               scoring.FULL_ORACLE: {"color": "0.55"},
               scoring.FULL_NOISE_ORACLE: {"color": "0.55", "ls": "--"}}
    return plots.save(plots.nrmse_curves(curves, "simulated single-antenna logs", shown,
                                         styles=oracles,
                                         ylabel="RMSE ratio to the oracle gyro EKF"), path)


main = entry("receiver_study", receiver_study)


if __name__ == "__main__":
    sys.exit(main())
