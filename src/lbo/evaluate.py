"""Score any observer, classical or learned, on the test grid; `python -m lbo.evaluate`.

The command: it reads the config, scores through :mod:`lbo.scoring.grid` (or
:mod:`lbo.scoring.logscore` on a user's logs), writes evaluation.csv and its figure, and tells
an observer's MLflow run.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from lbo.core.atomic import atomic_path, write_text
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.filters.classical import BOUND, DYNAMIC, LOG_PEERS, NAMES, OBSERVERS, TUNED
from lbo.filters.classical import estimate as run_classical
from lbo.scoring.grid import (
    REFERENCES,
    calibration,
    check_observers,
    classical_table,
    learned_nets,
    load_test,
    predict,
    predict_grid,
    predict_recursive,
    reference,
    score,
)
from lbo.scoring.outages import Outages
from lbo.sim.noise import Noise
from lbo.sim.schema import Trajectories
from lbo.sim.vehicle import Vehicle


def evaluate(cfg: DictConfig) -> Path:
    """Score the configured classical observers (and learned ones: ``learned``, and
    ``observer``, whose MLflow run is told the result); write evaluation.csv and its figure."""
    from lbo.logs.sets import is_logs

    observers = list(cfg.observers)
    learned = [str(s) for s in cfg.get("learned") or []]
    one = cfg.get("observer")
    if one is not None:  # an existing observer, scored first and its run told the result
        if not isinstance(one, str) or not one:
            raise LboError(f"observer must be a run id, a checkpoint or a models:/ URI, got "
                           f"{one!r} (a run id of digits only: quote it, observer=\"'<id>'\")")
        learned = [one, *learned]
        run_id = run_of(one)
    outages = Outages.from_cfg(cfg.get("outages"))  # its settings checked before any work
    if is_logs(cfg):
        if outages is not None:
            raise LboError("outages: scored on the simulated test grid; on a log with truth, "
                           "python -m lbo.observe outages.length_s=... scores them")
        csv, names, written = run_logs(cfg, observers, learned)
    else:
        csv, names, written = _run_grid(cfg, observers, learned, outages)
    if one is not None:
        log_to_run(run_id, one, names[0], csv, str(cfg.data.name), written)
    return csv


def run_of(source: str) -> str | None:
    """The MLflow run an observer source belongs to: a run id, ``runs:/<id>/...``, or the
    run of a ``models:/<name>/<version>``; None for a checkpoint file."""
    import re

    if re.fullmatch(r"[0-9a-f]{32}", source):
        return source
    if source.startswith("runs:/"):
        return source[len("runs:/"):].split("/")[0]
    if source.startswith("models:/"):
        import mlflow

        from lbo.core.paths import tracking_uri

        name, _, version = source[len("models:/"):].partition("/")
        try:
            return mlflow.MlflowClient(tracking_uri()).get_model_version(name, version).run_id
        except Exception:  # load_net names a missing model in one line before scoring
            return None
    return None


def log_to_run(run_id: str | None, source: str, name: str, csv: Path, data: str,
               files: list[Path] | None = None) -> None:
    """Log the scores of the observer ``source``, called ``name`` in ``csv``, to its MLflow run
    ``run_id``: metrics ``eval_<data>_nrmse_alpha_<a>`` per noise level (``eval_<data>_nrmse``
    pooled over a user's test logs; with an outages.csv among ``files``, also
    ``eval_<data>_outage_end_m_alpha_<a>``) and ``files``, the files this evaluation wrote (default:
    ``csv`` alone), under ``evaluations/<data>/``. Nothing else in their folder is uploaded: it
    may hold anything of the user's, and the tracking server may be shared."""
    import mlflow
    from mlflow.entities import Metric

    from lbo.core.paths import tracking_uri

    if run_id is None:
        print(f"note: {source} is a checkpoint file, not an MLflow run: the scores are in "
              f"{csv} only (give its run id to log them to the run)")
        return
    table = pd.read_csv(csv)
    rows = table[table["observer"] == name]
    stamp = int(time.time() * 1000)
    if "file" in rows:  # a user's test logs: the pooled row
        from lbo.scoring.logscore import ALL, drive_metrics

        pooled = rows[rows["file"] == ALL].iloc[0]
        metrics = {f"eval_{data}_nrmse": float(pooled["nrmse"]),
                   **drive_metrics(table, name, f"eval_{data}_")}
    else:
        metrics = {f"eval_{data}_nrmse_alpha_{a:g}": float(v)
                   for a, v in zip(rows["alpha"], rows["nrmse"])}
    for path in files or []:  # through GNSS outages: the error at an outage's end
        if Path(path).name == "outages.csv":
            through = pd.read_csv(path)
            through = through[through["estimator"] == name]
            metrics.update({f"eval_{data}_outage_end_m_alpha_{a:g}": float(v)
                            for a, v in zip(through["alpha"], through["end_m"])})
    client = mlflow.MlflowClient(tracking_uri())
    client.log_batch(run_id, metrics=[Metric(k.replace(".", "_"), v, stamp, 0)
                                      for k, v in metrics.items()])
    for path in files or [csv]:
        client.log_artifact(run_id, str(path), artifact_path=f"evaluations/{data}")
    print(f"logged to MLflow run {run_id}: {len(metrics)} metrics eval_{data}_*, and "
          f"evaluations/{data}/")


def _run_grid(cfg: DictConfig, observers: list[str], learned: list[str],
              outages: Outages | None = None) -> tuple[Path, list[str], list[Path]]:
    """The simulated test grid of ``cfg.data`` (or ``test_file``): evaluation.csv (and
    outages.csv through ``outages``), the names the ``learned`` observers have in it, in
    order, and every file written."""
    from lbo.core import plots
    from lbo.sim.datasets import build, spec_from_cfg
    from lbo.sim.truth import of_config as truth_of_config

    check_observers(observers)
    if cfg.metric.reference not in REFERENCES:
        raise LboError(f"metric.reference must be one of {list(REFERENCES)}, "
                       f"got {cfg.metric.reference!r}")
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    truth = truth_of_config(cfg, vehicle.wheelbase)
    nets = learned_nets(learned)  # every checkpoint read before any data is made
    keep = None  # the classical rows are kept beside lbo's data sets, not a user's file
    if cfg.get("test_file"):
        path = Path(cfg.test_file)
    else:
        folder, _, _ = build(spec_from_cfg(cfg))
        path = keep = folder / "test.parquet"
    if truth.car is not None:  # a car that slips: its oracle is the floor, the tuned
        if BOUND in observers:  # kinematic EKF the fair classical peer
            observers.remove(BOUND)
            print("note: pcrb left out: it is the kinematic bicycle's bound, and bounds nothing "
                  "on a car that slips")
        for name in (TUNED, DYNAMIC):
            if name not in observers:
                observers.insert(observers.index(BOUND) if BOUND in observers
                                 else len(observers), name)
    forms, calibrate, smooth = _extras(cfg)
    arr = load_test(path)
    if outages is not None:  # where they fall, before anything is scored
        from lbo.scoring.outages import grid_windows

        spans = grid_windows(arr, outages, vehicle.dt)
    ref = reference(arr, vehicle, noise, cfg.metric.reference)
    # estimates (and covariances) of everything that gives a covariance, for calibration
    # and smoothing: the classical filters, and the window filters in their recursive form
    covariant: dict[str, tuple[np.ndarray, np.ndarray]] = {
        name: run_classical(name, arr.m, arr.u, vehicle, noise, alpha=arr.alpha)
        for name in observers if name in OBSERVERS and (calibrate or smooth)}
    table = classical_table(arr, vehicle, noise, observers, ref, progress=True, truth=truth,
                            given={name: est for name, (est, _) in covariant.items()},
                            keep=keep)
    from lbo.scoring import lateral

    rows, names = [], []
    bodies: dict[str, np.ndarray] = {}  # the v_y, r a single-track body carried, by net
    for name, net in nets.items():
        from lbo.serve.runners import default_form, has_recursive_form, is_window_filter

        chosen = [default_form(net)] if forms is None else forms
        for form in chosen if has_recursive_form(net) else ["window"]:
            label = name if form == default_form(net) else f"{name}-{form}"
            if form == "window":
                est = predict_grid(net, arr, net.window)
            else:
                est, cov, body = predict_recursive(net, arr)
                if cov is not None:  # a KalmanNet's carried form gives none
                    covariant[label] = (est, cov)
                if body is not None and lateral.carries(net):  # a single-track body's v_y, r
                    bodies[name] = body
            rows.append(score(label, est, arr, ref))
            names.append(label)
            if form == "recursive" and smooth and is_window_filter(net):
                rows.append(score(f"{label}-smoothed",
                                  predict_recursive(net, arr, smooth=True)[0], arr, ref))
                names.append(f"{label}-smoothed")
    if smooth:
        for name in [o for o in observers if o in OBSERVERS]:
            est = run_classical(name, arr.m, arr.u, vehicle, noise, alpha=arr.alpha,
                                smooth=True, lengths=arr.lengths).mean
            rows.append(score(f"{name}-smoothed", est, arr, ref))
            observers.append(f"{name}-smoothed")
    table = pd.concat([*rows, table], ignore_index=True)
    observers = [*names, *observers]
    out = Path(cfg.output_dir)
    csv = out / "evaluation.csv"
    with atomic_path(csv) as tmp:
        table.to_csv(tmp, index=False)
    written = [csv, plots.save(plots.nrmse_curves(table, title="classical observers" if not nets
                                                  else "observers on the test grid"),
                               out / "nrmse_classical.png")]
    if calibrate:
        calibration(covariant, arr, out)
        written += [out / "nees.csv", out / "nees.png"]
    if truth.car is not None and arr.lateral is not None:  # the states no sensor gives
        written.append(_lateral(arr, vehicle, noise, truth, {
            name: bodies[name] if name in bodies else lateral.carried(net, arr)  # window form
            for name, net in nets.items() if lateral.carries(net)},
            {name: net.lateral_error for name, net in nets.items()}, out))
    with pd.option_context("display.width", 120, "display.precision", 4):
        pivot = table.pivot(index="alpha", columns="observer", values="nrmse")[observers]
        print(f"NRMSE (E_ref = {cfg.metric.reference}: {ref[0]:.3f} m, {ref[1]:.3f} m, "
              f"{ref[2] * 1e3:.2f} mrad)")
        print(pivot.to_string())
    print(f"evaluation: {csv}")
    if outages is not None:
        written.append(_outages(outages, spans, arr, vehicle, noise, truth,
                                [o for o in observers if o in NAMES and o != BOUND],
                                nets, out))
    return csv, list(nets), written


def _lateral(arr: Trajectories, vehicle: Vehicle, noise: Noise, truth: Any,
             bodies: dict[str, np.ndarray], errors: dict[str, np.ndarray | None],
             out: Path) -> Path:
    """lateral.csv: beta, v_y and r scored on a car that slips (:mod:`lbo.scoring.lateral`),
    first the learned observers' whose single-track body carried ``bodies`` (label -> (G, T,
    2) ``[v_y, r]``), with the body's ``errors`` their checkpoints hold; printed with beta in
    degrees."""
    from lbo.scoring import lateral

    scores = lateral.table(arr, vehicle, noise, truth, bodies, errors)
    path = out / "lateral.csv"
    with atomic_path(path) as tmp:
        scores.to_csv(tmp, index=False)
    print("side slip beta, lateral velocity v_y and yaw rate r, RMSE over the scored rows "
          "(a learned observer's where it carries a single-track body):")
    print(lateral.printable(scores))
    print(f"lateral states: {path}")
    return path


def _outages(outages: Outages, spans: np.ndarray, arr: Trajectories, vehicle: Vehicle,
             noise: Noise, truth: Any, classical: list[str], learned: dict[str, Any],
             out: Path) -> Path:
    """outages.csv: every observer through the GNSS outages ``spans`` (K, 3) cut into the test
    grid (:func:`lbo.scoring.outages.grid_table`), written and printed."""
    from lbo.scoring import outages as outage

    table = outage.grid_table(arr, spans, vehicle, noise, classical, learned, truth)
    path = out / "outages.csv"
    with atomic_path(path) as tmp:
        table.to_csv(tmp, index=False)
    print(f"through GNSS outages of {outages.length_s:g} s (every {outages.every_s:g} s while "
          f"moving, {len(spans)} in {len(np.unique(spans[:, 0]))} test trajectories; the fixes "
          "blanked, the truth kept): the position error at an outage's end (m)")
    print(outage.printable(table))
    print(f"outages: {path}")
    return path


def _extras(cfg: DictConfig) -> tuple[list[str] | None, bool, bool]:
    """The checked ``forms`` (None: each observer's default), ``calibration`` and ``smooth``
    settings."""
    from lbo.serve.runners import FORMS

    forms = cfg.get("forms")
    for form in forms or []:
        if form not in FORMS:
            raise LboError(f"forms: expected a list of {list(FORMS)}, got {form!r}")
    flags = []
    for key in ("calibration", "smooth"):
        value = cfg.get(key, False)
        if not isinstance(value, bool):
            raise LboError(f"{key} must be true or false, got {value!r}")
        flags.append(value)
    return (None if forms is None else list(forms)), flags[0], flags[1]


def run_logs(cfg: DictConfig, observers: list[str], learned: list[str]
             ) -> tuple[Path, list[str], list[Path]]:
    """``data=logs``: score the classical peers that run on a log (and ``learned``
    observers) on the test logs, pooled and per file (:mod:`lbo.scoring.logscore`); write
    evaluation.csv and nrmse_logs.png. Returns its path, the learned observers' names and the
    files written."""
    from lbo.core import plots
    from lbo.logs.sets import build, spec_from_cfg, test_files
    from lbo.scoring import logscore

    spec = spec_from_cfg(cfg, need=("test",))
    peers = [o for o in observers if o in LOG_PEERS]
    left_out = [o for o in observers if o not in LOG_PEERS]
    check_observers(observers)
    if "ekf" not in peers:
        peers.insert(0, "ekf")  # the reference of the NRMSE
    nets = learned_nets(learned)
    folder = build(spec)[0]
    arr = logscore.load(folder)
    estimates = {name: predict(net, arr) for name, net in nets.items()}
    estimates.update(logscore.peer_estimates(arr, spec.vehicle, spec.noise, peers))
    table = logscore.table(estimates, arr, test_files(folder))
    out = Path(cfg.output_dir)
    csv = out / "evaluation.csv"
    with atomic_path(csv) as tmp:
        table.to_csv(tmp, index=False)
    figure = plots.save(logscore.figure(table, "observers on the test logs"),
                        out / "nrmse_logs.png")
    written = [csv, figure]
    print(f"note: {logscore.NOTE}"
          + (f" (left out: {', '.join(left_out)})" if left_out else ""))
    print(f"pooled over {len(test_files(folder))} test log(s):")
    print(logscore.printable(table))
    if table["file"].nunique() > 2:  # two logs or more beside the pooled row: across drives
        from lbo.scoring.drives import markdown

        text = markdown(logscore.across(table))
        written.append(write_text(out / "drives.md", text))
        print("across the test logs, each one's NRMSE over the EKF's on it, their mean and "
              "the worst:")
        print(text, end="")
    print(f"evaluation: {csv}")
    return csv, list(nets), written


main = entry("evaluate", evaluate)


if __name__ == "__main__":
    sys.exit(main())
