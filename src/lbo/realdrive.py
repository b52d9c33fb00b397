"""`python -m lbo.realdrive`: a real car drive end to end, every classical observer on it.

    python -m lbo.realdrive [output_dir=reports/realdrive] [observers=[ekf,adaptive,ukf,gyro]]
                            [learn.epochs=12] [learn.objective=truth|innovations]
                            [across_drives=true] [nets=[<checkpoint>]] [net_fit.epochs=8]

Reads the onavdata hill drive (``pip install 'lbo[real]'``; :mod:`lbo.logs.hguide`), fits the
INS's boresight, the antenna's lever arm and the fixes' latency, and writes it as three lbo
logs, one per time span (:data:`lbo.logs.hguide.SPANS`): ``hill_train.parquet``,
``hill_val.parquet`` and ``hill_test.parquet``. Each takes ``python -m lbo.observe`` as it is.
It learns the gyro EKF's noise on the train span, keeping the best on the validation span
(:mod:`lbo.learn.gyro_fit`; ``gyro_noise.json``, which ``lbo.observe observer=gyro
gyro_noise=...`` reads). On the test span it scores, against the INS/GNSS truth at the
antenna:

- the raw fixes (position at the fix rows; heading: the course over ground of the receiver's
  velocity, where the car moves fast enough for it to be one);
- each classical observer with the receiver's channels (its reported accuracy as R, its
  velocity as the course), the gyro EKF with the learned noise, and the EKF without the
  channels (lbo's R, no velocity) and smoothed (RTS, offline), as :meth:`lbo.Observer.run`
  gives them;
- each learned observer of ``nets`` (checkpoints, MLflow run ids) with the receiver's channels
  (the robust observer's recursive form takes them); and, with ``net_fit.epochs``, each of
  them that reads a receiver (``experiment=receiver``) trained on the train span, fine-tuned
  from its weights and from scratch (:mod:`lbo.learn.net_fit`; ``<name>_finetuned.ckpt``,
  ``<name>_span.ckpt``).

Then, leave-one-drive-out (``across_drives``, :mod:`lbo.scoring.drives`): the drive holds
three drives, standing still between them (:func:`lbo.logs.hguide.drives`); for each, the gyro
EKF's noise is learned as ``learn`` says (its objective included) on the other two, and every
classical observer and that noise are scored on it (``drives.csv``, ``drives.md``: each
drive's ratio to the EKF, their mean and the worst; ``gyro_noise_without_drive<k>.json``).
Each of ``nets`` is scored on each drive as it was trained (on none of them), and with
``net_fit.epochs`` each that reads a receiver is also fine-tuned on the other two, the epoch
kept by the later of them (``<name>_without_drive<k>.ckpt``).

It writes ``results.csv`` and ``results.md`` (RMSE of x, y in m and psi in mrad, over the rows
each estimates, and the quadratic mean of the three RMSE ratios to the EKF's, :data:`RATIOS`),
``alignment.json`` and ``test.png`` (the learned gyro EKF's path and errors; without
learning, the first observer's), and prints the table.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import DictConfig

from lbo.core.atomic import atomic_path
from lbo.core.checks import boolean, integer, number, require
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.gyro_noise import GyroNoise
from lbo.learn.noise_run import ACROSS
from lbo.logs import hguide
from lbo.logs.io import check_log, check_output_path, write_table
from lbo.scoring import outages as outage
from lbo.scoring.outages import Outages
from lbo.scoring.receiver import (
    EKF,
    load_nets,
    markdown,
    moving_rows,
    net_rows,
    ratio_on_same_rows,
    ratio_to,
    score,
)
from lbo.sim.columns import STATE

__all__ = ["ACROSS", "FINE_TUNED", "FIT_FINE_TUNED", "FIT_KINDS", "FIT_OTHER_DRIVES", "FIT_SPAN",
           "KEEPS", "LEARNED", "RATIOS", "SIMULATED", "main", "realdrive"]

LEARNED = "gyro, noise learned on the train span"
"""The row of the gyro EKF whose noise :mod:`lbo.learn.gyro_fit` learned from the defaults."""
SIMULATED = "gyro, noise learned on simulated drives only"
"""... learned on simulated single-antenna drives, not on the real one."""
FINE_TUNED = "gyro, noise learned on simulated drives, fine-tuned on the train span"
"""... learned on simulated drives, then on the train span."""
FIT_FINE_TUNED = "fine-tuned on the train span"
"""The row of a net of ``nets`` trained on the train span from its own weights (its name
first)."""
FIT_SPAN = "trained on the train span only"
"""... from scratch, on the train span alone."""
FIT_OTHER_DRIVES = "fine-tuned on the other drives"
"""The row of a net of ``nets`` in leave-one-drive-out, trained on the drives other than the
one scored (the last of them kept for validation) from its own weights (its name first)."""
FIT_KINDS = ("finetuned", "span")
"""The checkpoints' suffixes: ``<name>_finetuned.ckpt``, ``<name>_span.ckpt``."""
KEEPS = ("same", "held_out")
"""``across_keep``: the drives that keep a fold's best epoch of the noise, the same it learns
on, or the last of them, held out of its learning (:func:`lbo.scoring.drives.kept_apart`)."""
RATIOS = ("vs_ekf", "vs_ekf_same_rows", "vs_ekf_moving")
"""The table's ratio columns: the measure against the EKF over the rows each estimates, over
the rows both estimate, and over those of them where the car moves
(:func:`lbo.scoring.receiver.moving_rows`: a course in the last 8 s)."""



def realdrive(cfg: DictConfig) -> dict[str, Any]:
    """Write the hill drive's span logs and score the classical observers on its test span."""
    from lbo.sim.noise import Noise
    from lbo.sim.vehicle import Vehicle

    observers = list(cfg.observers)
    for name in observers:
        classical.check(str(name), "observers")
    sources = [str(n) for n in cfg.get("nets") or ()]
    fit = {"epochs": integer(cfg.net_fit.epochs, "net_fit.epochs", 0),
           "lr": number(cfg.net_fit.lr, "net_fit.lr", 0.0, low_open=True),
           "lr_scratch": number(cfg.net_fit.lr_scratch, "net_fit.lr_scratch", 0.0,
                                low_open=True),
           "batch": integer(cfg.net_fit.batch, "net_fit.batch", 1),
           "seed": integer(cfg.net_fit.seed, "net_fit.seed", 0)}
    nets = load_nets(sources)  # after the settings: each checkpoint read once, before any work
    trainable = {s: obs for s, obs in zip(sources, nets)
                 if getattr(obs.net, "receiver", False)} if fit["epochs"] else {}
    names = [obs.name for obs in trainable.values()]
    if len(set(names)) < len(names):
        raise LboError(f"nets: two nets named {max(names, key=names.count)} to train on the "
                       "train span (net_fit.epochs > 0); give one at a time")
    from lbo.learn.gyro_fit import Settings

    learn = Settings.from_cfg(cfg.learn)
    simulated_epochs = integer(cfg.learn.simulated, "learn.simulated", 0)
    across_drives = boolean(cfg.get("across_drives", True), "across_drives")
    keep = cfg.get("across_keep", "same")
    require(keep in KEEPS, "across_keep", f"one of {list(KEEPS)}", keep)
    outages = Outages.from_cfg(cfg.get("outages"))
    out = Path(str(cfg.output_dir))
    paths = {k: check_output_path(out / f"hill_{k}.parquet") for k in hguide.SPANS}
    check_output_path(out / "results.csv")
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    df = hguide.read()
    alignment = hguide.fit_alignment(df)
    log = hguide.to_log(df, vehicle, alignment)
    parts = hguide.spans(log)
    spans = outage.place(parts["test"], outages, vehicle.dt) if outages is not None else None
    out.mkdir(parents=True, exist_ok=True)
    for k, part in parts.items():
        check_log(part, f"hill drive, {k} span")
        write_table(part, paths[k])
    print(f"hill drive: {len(log)} rows at {vehicle.dt:g} s, {int(log['x_m'].notna().sum())} "
          f"fixes; boresight {1e3 * alignment.boresight:+.1f} mrad, lever arm "
          f"{alignment.lever[0]:+.2f} m forward, {alignment.lever[1]:+.2f} m left, latency "
          f"{alignment.latency:.2f} s (fit on {alignment.fixes} fixes above "
          f"{hguide.FIT_SPEED:g} m/s: RMS offset {alignment.rms_before:.2f} m -> "
          f"{alignment.rms_after:.2f} m)")
    print("spans: " + ", ".join(f"{k} {len(p) * vehicle.dt:.0f} s -> {paths[k]}"
                                for k, p in parts.items()))
    learned = (_learn(learn, simulated_epochs, cfg.simulated, parts, vehicle, noise, out)
               if learn.epochs else {})
    fitted = _fit_nets(fit, trainable, parts, out)
    every_net = {**net_rows(nets), **fitted}
    table, estimates = score(parts["test"], observers, vehicle, noise, learned, nets=every_net)
    table["vs_ekf"] = ratio_to(table, EKF)
    truth = parts["test"][list(STATE)].to_numpy(float)
    table["vs_ekf_same_rows"] = ratio_on_same_rows(table, estimates, truth, EKF)
    table["vs_ekf_moving"] = ratio_on_same_rows(table, estimates, truth, EKF,
                                                moving_rows(parts["test"], vehicle.dt))
    write_table(table, out / "results.csv")
    with atomic_path(out / "results.md") as tmp:
        Path(tmp).write_text(markdown(table, *RATIOS))
    with atomic_path(out / "alignment.json") as tmp:
        Path(tmp).write_text(json.dumps({"boresight_mrad": 1e3 * alignment.boresight,
                                         "lever_forward_m": float(alignment.lever[0]),
                                         "lever_left_m": float(alignment.lever[1]),
                                         "latency_s": alignment.latency,
                                         "rms_before_m": alignment.rms_before,
                                         "rms_after_m": alignment.rms_after,
                                         "fixes": alignment.fixes}, indent=1) + "\n")
    test = parts["test"]
    from lbo.core import plots

    best = (LEARNED if learned
            else f"{observers[0]}, receiver's accuracy and velocity")
    plots.save(plots.observed_log(test["t"].to_numpy(), test[["x_m", "y_m", "psi_m"]].to_numpy(),
                                  estimates[best], best, test[list(STATE)].to_numpy()),
               out / "test.png")
    print(f"test span ({len(test) * vehicle.dt:.0f} s), RMSE against the INS/GNSS truth "
          "at the antenna:")
    print(markdown(table, *RATIOS), end="")
    print(f"written: {out / 'results.md'}, {out / 'test.png'}")
    through = (_outages(outages, spans, test, observers, vehicle, noise, learned, every_net,
                        out) if outages is not None and spans is not None else None)
    drives = None
    if across_drives and (learn.epochs or nets):
        drives = _across_drives(learn, observers, hguide.drives(log), vehicle, noise, out,
                                nets=nets, trainable=trainable, fit=fit,
                                held_out=keep == "held_out")
    return {"table": table, "alignment": alignment, "paths": paths, "drives": drives,
            "outages": through}


def _outages(outages: Outages, spans: Any, test: pd.DataFrame, observers: list[str],
             vehicle: Any, noise: Any, learned: dict[str, GyroNoise], nets: dict[str, Any],
             out: Path) -> pd.DataFrame:
    """Every observer of the test span's table through the GNSS outages ``spans`` (K, 2) cut
    into it (:mod:`lbo.scoring.outages`): ``outages.csv``, ``outages.md`` and
    ``outages.png`` (the position error through an outage), printed; returns the table."""
    import numpy as np

    from lbo.core import plots

    _, estimates = score(outage.blank(test, spans), observers, vehicle, noise, learned,
                         nets=nets)
    table = outage.score(estimates, test, spans, vehicle.dt, reference=EKF)
    write_table(table, out / "outages.csv")
    with atomic_path(out / "outages.md") as tmp:
        Path(tmp).write_text(outage.markdown(table))
    seconds = np.arange(spans[0, 1] - spans[0, 0]) * vehicle.dt
    truth = test[list(STATE)].to_numpy(float)
    plots.save(plots.outage_errors(seconds, {k: outage.curves(e, truth, spans)
                                             for k, e in estimates.items()}),
               out / "outages.png")
    print(f"through {len(spans)} GNSS outages of {outages.length_s:g} s (every "
          f"{outages.every_s:g} s while moving) on the test span, every receiver column "
          "blanked:")
    print(outage.markdown(table), end="")
    print(f"written: {out / 'outages.md'}, {out / 'outages.png'}")
    return table


def _learn(cfg: Any, simulated_epochs: int, simulated: DictConfig,
           parts: dict[str, pd.DataFrame], vehicle: Any, noise: Any, out: Path
           ) -> dict[str, GyroNoise]:
    """The gyro EKF's noise learned on the train span from the defaults as ``cfg``
    (:class:`lbo.learn.gyro_fit.Settings`) says, and, with ``simulated_epochs``, first on
    simulated drives (:func:`lbo.simulate.simulate` of ``simulated``: ``simulated.drives`` to
    train on from its seed on, half as many after them to validate on) and then fine-tuned on
    the train span; each kept by its validation drives. Written as ``gyro_noise.json`` (from
    the defaults), ``gyro_noise_simulated.json``, ``gyro_noise_finetuned.json`` and their
    ``*_history.csv``. Returns the noises by row label."""
    import dataclasses

    from lbo.learn import gyro_fit

    R = gyro_fit.fix_cov(noise)

    def learn(name: str, train: pd.DataFrame | list[pd.DataFrame],
              val: pd.DataFrame | list[pd.DataFrame], start: GyroNoise, epochs: int,
              where: str) -> GyroNoise:
        settings = dataclasses.replace(cfg, epochs=epochs)
        return gyro_fit.fit_and_write(out, name, train, val, vehicle, R, start, where,
                                      **settings.kwargs(vehicle.dt))

    defaults = cfg.start(noise.Q)
    out_noise = {LEARNED: learn("gyro_noise", parts["train"], parts["val"], defaults,
                                cfg.epochs, "on the train span, from the defaults")}
    if simulated_epochs:
        from lbo.simulate import simulate

        seed = integer(simulated.seed, "simulated.seed", 0)
        drives = integer(simulated.drives, "simulated.drives", 2)
        logs = [simulate(simulated, seed + i) for i in range(drives + drives // 2)]
        sim = learn("gyro_noise_simulated", logs[:drives], logs[drives:], defaults,
                    simulated_epochs, f"on {drives} simulated drives ({simulated.manoeuvre}, "
                    f"receiver {simulated.receiver.name})")
        out_noise[SIMULATED] = sim
        out_noise[FINE_TUNED] = learn("gyro_noise_finetuned", parts["train"], parts["val"], sim,
                                      cfg.epochs, "on the train span, from the simulated "
                                      "drives'")
    return out_noise


def _across_drives(cfg: Any, observers: list[str], drives: list[pd.DataFrame],
                   vehicle: Any, noise: Any, out: Path, nets: Sequence[Any] = (),
                   trainable: Mapping[str, Any] | None = None,
                   fit: Mapping[str, Any] | None = None, held_out: bool = False
                   ) -> pd.DataFrame:
    """Leave-one-drive-out (:mod:`lbo.scoring.drives`): for each of the drive's drives, the
    gyro EKF's noise learned from the defaults on the others as ``cfg``
    (:class:`lbo.learn.gyro_fit.Settings`) says (each fold's best epoch kept by those same
    drives, or with ``held_out`` learned on all but the last and kept by the last), every
    observer scored on it, and each of
    ``nets`` (learned observers) as it is; with ``fit["epochs"]``, each of ``trainable`` (by
    source: those that read a receiver) also fine-tuned on the others (:func:`_fold_nets`).
    Writes ``drives.csv`` (each drive's RMSE and ratio) and ``drives.md`` (the ratios to the
    EKF per drive, their mean and the worst), prints the latter and returns the summary."""
    from lbo.learn.noise_run import across_drives
    from lbo.scoring import drives as across

    trainable = dict(trainable or {})
    what = []
    if cfg.epochs:
        how = "truth" if cfg.objective == "truth" else "innovations' likelihood, no truth read"
        if cfg.receiver_noise == "variogram":
            how += ", the receiver's noise by its variogram"
        kept = "by the last of them" if held_out else "by the same drives"
        what.append(f"the gyro EKF's noise learned on the others ({cfg.epochs} epochs, {how}; "
                    f"the epoch kept {kept})")
    if nets:
        what.append(f"{len(nets)} learned observer(s) as trained" + (
            f", and {len(trainable)} fine-tuned on the others ({fit['epochs']} epochs)"
            if trainable and fit is not None else ""))
    print(f"leave-one-drive-out over {len(drives)} drives: {'; '.join(what)}, scored on each")
    table = across_drives(drives, cfg, vehicle, noise, observers, out,
                          progress=lambda line: print("  " + line), held_out=held_out,
                          nets=(lambda k, train: _fold_nets(k, train, nets, trainable, fit,
                                                            out)) if nets else None)
    wide = across.summary(table)
    write_table(table, out / "drives.csv")
    with atomic_path(out / "drives.md") as tmp:
        Path(tmp).write_text(across.markdown(wide))
    print("each drive scored by what was learned on the others (ratio to the EKF):")
    print(across.markdown(wide), end="")
    print(f"written: {out / 'drives.md'}, {out / 'drives.csv'}")
    return wide


def _fold_nets(k: int, train: list[pd.DataFrame], nets: Sequence[Any],
               trainable: Mapping[str, Any], fit: Mapping[str, Any] | None,
               out: Path) -> dict[str, Any]:
    """The learned observers of leave-one-drive-out's fold ``k`` (drive k + 1 left out), by
    row label: each of ``nets`` as it is, and each of ``trainable`` (by source) fine-tuned
    from its weights as ``fit`` says on the fold's drives but the last, kept by the last (a
    drive it does not train on: a fine-tuning that does not hold on another drive is not
    kept), written as ``<name>_without_drive<k + 1>.ckpt``."""
    from lbo.learn.net_fit import fit_and_write
    from lbo.scoring import drives as across
    from lbo.serve.observer import Observer

    rows = net_rows(list(nets))
    if fit is None or not fit["epochs"]:
        return rows
    fit_on, keep_by = across.kept_apart(train)
    for source, obs in trainable.items():
        path = fit_and_write(out / f"{obs.name}_without_drive{k + 1}.ckpt", source, fit_on,
                             keep_by, f"on the hill drive's drives but drive {k + 1}",
                             fresh=False, epochs=fit["epochs"], lr=fit["lr"],
                             batch=fit["batch"], seed=fit["seed"])
        rows[f"{obs.name}, {FIT_OTHER_DRIVES}"] = Observer.load(path)
    return rows


def _fit_nets(cfg: dict[str, Any], nets: dict[str, Any], parts: dict[str, pd.DataFrame],
              out: Path) -> dict[str, Any]:
    """Each net (by source) that reads a receiver trained on the train span, kept by the
    validation span (:mod:`lbo.learn.net_fit`): fine-tuned from its weights, and from scratch.
    Written as ``<name>_finetuned.ckpt`` and ``<name>_span.ckpt`` with their
    ``*_history.csv``; returns them loaded, by row label."""
    from lbo.learn.net_fit import fit_and_write
    from lbo.serve.observer import Observer

    found = {}
    for source, obs in nets.items():
        for kind, fresh, label in zip(FIT_KINDS, (False, True), (FIT_FINE_TUNED, FIT_SPAN)):
            path = fit_and_write(out / f"{obs.name}_{kind}.ckpt", source, [parts["train"]],
                                 [parts["val"]], "on the hill drive's train span", fresh=fresh,
                                 epochs=cfg["epochs"],
                                 lr=cfg["lr_scratch"] if fresh else cfg["lr"],
                                 batch=cfg["batch"], seed=cfg["seed"])
            found[f"{obs.name}, {label}"] = Observer.load(path)
    return found


main = entry("realdrive", realdrive)


if __name__ == "__main__":
    sys.exit(main())
