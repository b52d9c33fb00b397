"""Score any observer, classical or learned, on the test grid; `python -m lbo.evaluate`.

Every observer is scored on the same points: the ``scored`` rows of the test set (after each
manoeuvre's run-in), pooled per alpha level. The learned observers' evaluation callback uses
:func:`score` and :func:`classical_table` from here.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from lbo import schema
from lbo.atomic import atomic_path
from lbo.classical import BOUND, DYNAMIC, NAMES, OBSERVERS, TUNED, measurement_cov
from lbo.classical import run as run_classical
from lbo.cli import entry
from lbo.errors import LboError
from lbo.filters import ekf_batch, pcrb
from lbo.metrics import PAPER_REFERENCE, SCORE_COLUMNS, rmse, score_table
from lbo.noise import Noise
from lbo.truth import Truth
from lbo.vehicle import Vehicle

CLASSICAL = NAMES
"""What ``observers=`` may name: the classical observers and the PCRB."""
REFERENCES = ("ekf", "paper")
Q_GRID = ((0.1, 0.3, 1.0, 3.0), (0.3, 1.0, 3.0, 10.0, 30.0))
"""Factors on the noise preset's process sigmas (position, heading) that ``oracle_tuned`` tries."""


def load_test(path: str | Path) -> dict[str, np.ndarray]:
    """Read a test set (Parquet with the evaluation schema) into padded arrays.

    Returns the dict of :func:`lbo.schema.to_arrays`: ``z, m`` (G, T, 3), ``u`` (G, T, 2),
    ``mask`` (G, T) scored steps, ``alpha`` (G,), with G = trajectories x alpha levels.
    Steps without a position fix (``x_m, y_m, psi_m`` all empty) are NaN rows of ``m``.
    """
    return schema.to_arrays(schema.read_set(path, schema.EVAL_COLUMNS, missing_fixes=True))


def classical(name: str, arr: dict[str, np.ndarray], vehicle: Vehicle, noise: Noise,
              progress: bool = False, seed: int = 0, truth: Truth | None = None) -> np.ndarray:
    """Estimates (G, T, 3) of classical observer ``name`` (:mod:`lbo.classical`) on the padded
    test arrays; the oracles are told each trajectory's alpha (``oracle_dynamic`` also the
    ``truth`` the set was drawn from). For ``pcrb`` the result is the bound's standard
    deviation per step, not an estimate: the kinematic bicycle's, with the truth's own process
    noise, so it bounds nothing on a car that slips (refused there).
    """
    check_observers([name])
    if name == BOUND:
        if truth is not None and truth.car is not None:
            raise LboError("pcrb: the bound is the kinematic bicycle's; it bounds nothing on a "
                           "car that slips (truth=dynamic)")
        R = measurement_cov("oracle", noise, arr["alpha"], len(arr["alpha"]))
        scale = 1.0 if truth is None else truth.process_scale
        return np.sqrt(pcrb(arr["z"], arr["u"], vehicle, scale**2 * noise.Q, R, rng=seed))
    return run_classical(name, arr["m"], arr["u"], vehicle, noise, alpha=arr["alpha"],
                         progress=progress, truth=truth)


def check_observers(names: Sequence[str], field: str = "observers") -> None:
    """Raise LboError naming ``field`` and the first name that is not a classical observer."""
    for name in names:
        if name not in CLASSICAL:
            raise LboError(f"{field}: unknown observer {name!r}; "
                           f"expected names from {list(CLASSICAL)}")


def reference(arr: dict[str, np.ndarray], vehicle: Vehicle, noise: Noise,
              mode: str = "ekf") -> np.ndarray:
    """E_ref (3,) for the NRMSE: our EKF's RMSE at alpha=1 (``ekf``) or the paper's constants."""
    if mode == "paper":
        return np.asarray(PAPER_REFERENCE)
    if mode != "ekf":
        raise LboError(f"metric.reference must be one of {list(REFERENCES)}, got {mode!r}")
    at1 = np.isclose(arr["alpha"], 1.0)
    if not at1.any():
        raise LboError("metric.reference=ekf needs alpha=1 in the test grid; "
                       "use metric.reference=paper")
    sub = {k: v[at1] for k, v in arr.items() if isinstance(v, np.ndarray) and len(v) == len(at1)}
    est = run_classical("ekf", sub["m"], sub["u"], vehicle, noise)
    return _pooled_rmse(est, sub["z"], sub["mask"])


def _pooled_rmse(est: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3,) RMSE over every masked step of every trajectory together."""
    return rmse(est.reshape(1, -1, 3), truth.reshape(1, -1, 3), mask.reshape(1, -1))[0]


def score(observer: str, est: np.ndarray, arr: dict[str, np.ndarray],
          ref: np.ndarray) -> pd.DataFrame:
    """Rows ``observer, alpha, rmse_x, rmse_y, rmse_psi, nrmse`` of estimates (G, T, 3).

    Steps outside ``arr["mask"]`` are ignored and may hold NaN.
    """
    return score_table(observer, est, arr["z"], arr["mask"], arr["alpha"], ref)


def bound_table(std: np.ndarray, arr: dict[str, np.ndarray], ref: np.ndarray) -> pd.DataFrame:
    """PCRB rows: the root of the mean bound variance over the scored points of each level.

    Scoring ``truth + std`` as an estimate gives exactly that, since its squared error at
    each step is the bound's variance.
    """
    return score("pcrb", arr["z"] + std, arr, ref)


def classical_table(arr: dict[str, np.ndarray], vehicle: Vehicle, noise: Noise,
                    observers: Sequence[str] = CLASSICAL, ref: np.ndarray | None = None,
                    progress: bool = False, seed: int = 0,
                    truth: Truth | None = None,
                    given: dict[str, np.ndarray] | None = None) -> pd.DataFrame:
    """Score the classical observers on the test arrays; ``ref`` defaults to our EKF's;
    ``truth``: what the set was drawn from, for ``oracle_dynamic``; ``given``: estimates
    (G, T, 3) already made, by name, which are scored instead of running that filter again."""
    check_observers(observers)
    ref = reference(arr, vehicle, noise) if ref is None else ref
    tables = []
    for name in observers:
        if name == TUNED:
            tables.append(score(name, tuned_oracle(arr, vehicle, noise, ref)[0], arr, ref))
            continue
        out = (given or {}).get(name)
        if out is None:
            out = classical(name, arr, vehicle, noise, progress=progress, seed=seed, truth=truth)
        tables.append(bound_table(out, arr, ref) if name == "pcrb" else score(name, out, arr, ref))
    return pd.concat(tables, ignore_index=True)[list(SCORE_COLUMNS)]


def tuned_oracle(arr: dict[str, np.ndarray], vehicle: Vehicle, noise: Noise,
                 ref: np.ndarray) -> tuple[np.ndarray, pd.DataFrame]:
    """The kinematic EKF told each level's alpha, its Q tuned per level on the scored points.

    Every pair of factors in :data:`Q_GRID` scales the preset's process sigmas (x and y by the
    first, psi by the second); at each alpha level the pair with the lowest NRMSE there wins.
    Returns the winners' estimates (G, T, 3) and a table ``alpha, position, heading`` of the
    factors chosen.
    """
    R = measurement_cov("oracle", noise, arr["alpha"], len(arr["alpha"]))
    sigma = np.asarray(noise.process_sigma)
    best_est = np.full_like(arr["m"], np.nan)
    best = {}  # alpha -> (nrmse, position factor, heading factor)
    for fp in Q_GRID[0]:
        for fh in Q_GRID[1]:
            Q = np.diag(np.square(sigma * [fp, fp, fh]))
            est = ekf_batch(arr["m"], arr["u"], vehicle, Q, R)
            for a, nrmse in score(TUNED, est, arr, ref)[["alpha", "nrmse"]].itertuples(
                    index=False):
                if a not in best or nrmse < best[a][0]:
                    best[a] = (nrmse, fp, fh)
                    rows = np.isclose(arr["alpha"], a)
                    best_est[rows] = est[rows]
    chosen = pd.DataFrame([(a, fp, fh) for a, (_, fp, fh) in sorted(best.items())],
                          columns=["alpha", "position", "heading"])
    return best_est, chosen


def nrmse_at(table: pd.DataFrame, observer: str, alpha: float) -> float:
    """The NRMSE of ``observer`` at ``alpha`` in a score table."""
    row = table[(table["observer"] == observer) & np.isclose(table["alpha"], alpha)]
    if row.empty:
        raise LboError(f"no row for observer {observer!r} at alpha={alpha}")
    return float(row["nrmse"].iloc[0])


def oracle_ratio(table: pd.DataFrame, observer: str, low: float = 0.25,
                 high: float = 6.0, oracle: str = "oracle") -> pd.Series:
    """NRMSE of ``observer`` over the oracle EKF's, per alpha in [low, high] (index alpha).

    The oracle is told each level's alpha, so it is the practical floor of a causal observer;
    a ratio of 1.1 means 10 % above that floor. ``oracle="oracle_dynamic"``: the floor on a
    car that slips.
    """
    piv = table.pivot_table(index="alpha", columns="observer", values="nrmse")
    for name in (observer, oracle):
        if name not in piv:
            raise LboError(f"no rows for observer {name!r} in the score table")
    keep = (piv.index >= low - 1e-9) & (piv.index <= high + 1e-9)
    return (piv[observer] / piv[oracle])[keep].rename(f"ratio_to_{oracle}")


def run(cfg: DictConfig) -> Path:
    """Score the configured classical observers (and learned ones: ``learned``, and
    ``observer``, whose MLflow run is told the result); write evaluation.csv and its figure."""
    from lbo.datagen.logs import is_logs

    observers = list(cfg.observers)
    learned = [str(s) for s in cfg.get("learned") or []]
    one = cfg.get("observer")
    if one is not None:  # an existing observer, scored first and its run told the result
        if not isinstance(one, str) or not one:
            raise LboError(f"observer must be a run id, a checkpoint or a models:/ URI, got "
                           f"{one!r} (a run id of digits only: quote it, observer=\"'<id>'\")")
        learned = [one, *learned]
        run_id = run_of(one)
    if is_logs(cfg):
        csv, names = run_logs(cfg, observers, learned)
    else:
        csv, names = _run_grid(cfg, observers, learned)
    if one is not None:
        log_to_run(run_id, one, names[0], csv, str(cfg.data.name))
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

        from lbo.paths import tracking_uri

        name, _, version = source[len("models:/"):].partition("/")
        try:
            return mlflow.MlflowClient(tracking_uri()).get_model_version(name, version).run_id
        except Exception:  # load_net names a missing model in one line before scoring
            return None
    return None


def log_to_run(run_id: str | None, source: str, name: str, csv: Path, data: str) -> None:
    """Log the scores of the observer ``source``, called ``name`` in ``csv``, to its MLflow run
    ``run_id``: metrics ``eval_<data>_nrmse_alpha_<a>`` per noise level (``eval_<data>_nrmse``
    pooled over a user's test logs) and the evaluation files under ``evaluations/<data>/``."""
    import mlflow
    from mlflow.entities import Metric

    from lbo.paths import tracking_uri

    if run_id is None:
        print(f"note: {source} is a checkpoint file, not an MLflow run: the scores are in "
              f"{csv} only (give its run id to log them to the run)")
        return
    table = pd.read_csv(csv)
    rows = table[table["observer"] == name]
    stamp = int(time.time() * 1000)
    if "file" in rows:  # a user's test logs: the pooled row
        from lbo.logscore import ALL

        pooled = rows[rows["file"] == ALL].iloc[0]
        metrics = {f"eval_{data}_nrmse": float(pooled["nrmse"])}
    else:
        metrics = {f"eval_{data}_nrmse_alpha_{a:g}": float(v)
                   for a, v in zip(rows["alpha"], rows["nrmse"])}
    client = mlflow.MlflowClient(tracking_uri())
    client.log_batch(run_id, metrics=[Metric(k.replace(".", "_"), v, stamp, 0)
                                      for k, v in metrics.items()])
    for path in sorted(csv.parent.glob("*.csv")) + sorted(csv.parent.glob("*.png")):
        client.log_artifact(run_id, str(path), artifact_path=f"evaluations/{data}")
    print(f"logged to MLflow run {run_id}: {len(metrics)} metrics eval_{data}_*, and "
          f"evaluations/{data}/")


def _run_grid(cfg: DictConfig, observers: list[str], learned: list[str]
              ) -> tuple[Path, list[str]]:
    """The simulated test grid of ``cfg.data`` (or ``test_file``): evaluation.csv, and the
    names the ``learned`` observers have in it, in order."""
    from lbo import plots
    from lbo.datagen.build import build, spec_from_cfg
    from lbo.truth import from_cfg as truth_from_cfg

    check_observers(observers)
    if cfg.metric.reference not in REFERENCES:
        raise LboError(f"metric.reference must be one of {list(REFERENCES)}, "
                       f"got {cfg.metric.reference!r}")
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    truth = truth_from_cfg(cfg.get("truth"), vehicle.wheelbase)
    nets = learned_nets(learned)  # every checkpoint read before any data is made
    if cfg.get("test_file"):
        path = Path(cfg.test_file)
    else:
        folder, _, _ = build(spec_from_cfg(cfg))
        path = folder / "test.parquet"
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
    ref = reference(arr, vehicle, noise, cfg.metric.reference)
    # estimates (and covariances) of everything that gives a covariance, for calibration
    # and smoothing: the classical filters, and the window filters in their recursive form
    covariant = {name: run_classical(name, arr["m"], arr["u"], vehicle, noise,
                                     alpha=arr["alpha"], return_cov=True)
                 for name in observers if name in OBSERVERS and (calibrate or smooth)}
    table = classical_table(arr, vehicle, noise, observers, ref, progress=True, truth=truth,
                            given={name: est for name, (est, _) in covariant.items()})
    rows, names = [], []
    for name, net in nets.items():
        from lbo.observer import default_form

        chosen = [default_form(net)] if forms is None else forms
        for form in chosen if getattr(net, "physical", False) else ["window"]:
            label = name if form == default_form(net) else f"{name}-{form}"
            if form == "window":
                est = predict_grid(net, arr, net.window)
            else:
                est, cov = predict_recursive(net, arr)
                covariant[label] = (est, cov)
            rows.append(score(label, est, arr, ref))
            names.append(label)
            if form == "recursive" and smooth:
                rows.append(score(f"{label}-smoothed",
                                  predict_recursive(net, arr, smooth=True)[0], arr, ref))
                names.append(f"{label}-smoothed")
    if smooth:
        for name in [o for o in observers if o in OBSERVERS]:
            est = run_classical(name, arr["m"], arr["u"], vehicle, noise, alpha=arr["alpha"],
                                smooth=True, lengths=arr["lengths"])
            rows.append(score(f"{name}-smoothed", est, arr, ref))
            observers.append(f"{name}-smoothed")
    table = pd.concat([*rows, table], ignore_index=True)
    observers = [*names, *observers]
    out = Path(cfg.output_dir)
    csv = out / "evaluation.csv"
    with atomic_path(csv) as tmp:
        table.to_csv(tmp, index=False)
    plots.save(plots.nrmse_curves(table, title="classical observers" if not nets else
                                  "observers on the test grid"),
               out / "nrmse_classical.png")
    if calibrate:
        calibration(covariant, arr, out)
    with pd.option_context("display.width", 120, "display.precision", 4):
        pivot = table.pivot(index="alpha", columns="observer", values="nrmse")[observers]
        print(f"NRMSE (E_ref = {cfg.metric.reference}: {ref[0]:.3f} m, {ref[1]:.3f} m, "
              f"{ref[2] * 1e3:.2f} mrad)")
        print(pivot.to_string())
    print(f"evaluation: {csv}")
    return csv, list(nets)


def _extras(cfg: DictConfig) -> tuple[list[str] | None, bool, bool]:
    """The checked ``forms`` (None: each observer's default), ``calibration`` and ``smooth``
    settings."""
    from lbo.observer import FORMS

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


def calibration(covariant: dict[str, tuple[np.ndarray, np.ndarray]], arr: dict[str, np.ndarray],
                out: Path) -> pd.DataFrame:
    """NEES per alpha of every observer that gives a covariance (:func:`lbo.metrics.nees_table`);
    writes ``nees.csv`` and ``nees.png`` to ``out`` and prints the table."""
    from lbo import plots
    from lbo.metrics import nees_table

    table = pd.concat([nees_table(name, est, cov, arr["z"], arr["mask"], arr["alpha"])
                       for name, (est, cov) in covariant.items()], ignore_index=True)
    with atomic_path(out / "nees.csv") as tmp:
        table.to_csv(tmp, index=False)
    plots.save(plots.nees_curves(table), out / "nees.png")
    with pd.option_context("display.width", 120, "display.precision", 3):
        print("mean NEES per alpha (3 for a consistent filter; the 95% band of a mean over "
              "the level's trajectories in brackets):")
        piv = table.pivot(index="alpha", columns="observer", values="nees")
        band = table.drop_duplicates("alpha").set_index("alpha")[["low", "high"]]
        print(piv.join(band).to_string())
    print(f"calibration: {out / 'nees.csv'}")
    return table


def learned_nets(sources: Sequence[str]) -> dict:
    """name (``cnn-N20``, ...) -> the net of each learned observer in ``sources`` (checkpoint
    files, MLflow run ids, runs:/ or models:/ URIs), all read before any scoring starts."""
    from lbo.observer import load_net

    nets: dict = {}
    for source in sources:
        net, hp = load_net(source)
        name = base = f"{hp['model']['name']}-N{hp['window']}"
        i = 2
        while name in nets:  # two observers of one architecture and window
            name, i = f"{base}-{i}", i + 1
        nets[name] = net
    return nets


def run_logs(cfg: DictConfig, observers: list[str], learned: list[str]
             ) -> tuple[Path, list[str]]:
    """``data=logs``: score the classical peers that run on a log (and ``learned``
    observers) on the test logs, pooled and per file (:mod:`lbo.logscore`); write
    evaluation.csv and nrmse_logs.png. Returns its path and the learned observers' names."""
    from lbo import logscore, plots
    from lbo.datagen.logs import build, spec_from_cfg, test_files

    spec = spec_from_cfg(cfg, need=("test",))
    peers = [o for o in observers if o in logscore.PEERS]
    left_out = [o for o in observers if o not in logscore.PEERS]
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
    plots.save(logscore.figure(table, "observers on the test logs"), out / "nrmse_logs.png")
    print(f"note: {logscore.NOTE}"
          + (f" (left out: {', '.join(left_out)})" if left_out else ""))
    print(f"pooled over {len(test_files(folder))} test log(s):")
    print(logscore.printable(table))
    print(f"evaluation: {csv}")
    return csv, list(nets)


main = entry("evaluate", run)


def predict_recursive(net, arr: dict[str, np.ndarray], device: str = "cpu",
                      smooth: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A window filter (an ObserverNet of ``filternet``) in its recursive form over every
    trajectory of the padded test arrays, all at once: (G, T, 3) estimates and (G, T, 3, 3)
    covariances, NaN outside the scored steps (``smooth``: the RTS smoother's)."""
    from lbo.models.recursive import run_arrays

    est, cov = run_arrays(net.net, arr["m"], arr["u"], smooth, arr["lengths"], device)
    est[~arr["mask"]] = np.nan
    cov[~arr["mask"]] = np.nan
    return est, cov


def predict(net, arr: dict[str, np.ndarray], batch_size: int = 8192,
            device: str = "cpu") -> np.ndarray:
    """A learned observer's estimates (G, T, 3) on the padded test arrays, in the form
    :class:`lbo.Observer` runs it by default (:func:`lbo.observer.default_form`)."""
    from lbo.observer import default_form

    if default_form(net) == "recursive":
        return predict_recursive(net, arr, device)[0]
    return predict_grid(net, arr, net.window, batch_size, device)


def predict_grid(net, arr: dict[str, np.ndarray], window: int, batch_size: int = 8192,
                 device: str = "cpu") -> np.ndarray:
    """Run a learned observer on every scored step of the padded test arrays.

    Parameters
    ----------
    net : a module mapping windows (B, N, 5) to states (B, 3), e.g. an ObserverNet.
    arr : padded test arrays from :func:`load_test`.

    Returns
    -------
    (G, T, 3) estimates at the scored steps, NaN elsewhere.
    """
    import torch

    from lbo.features import window_view

    g, t = arr["mask"].shape
    if window - 1 > int(np.argmax(arr["mask"], axis=1).min()):
        raise LboError(f"window={window} is longer than the test set's run-in")
    series = torch.from_numpy(np.concatenate([arr["m"], arr["u"]], axis=-1))  # (G, T, 5)
    windows = window_view(series, window)  # (G, T-N+1, N, 5) view
    gi, ti = np.nonzero(arr["mask"])
    est = np.full((g, t, 3), np.nan)
    net = net.to(device).eval()
    with torch.inference_mode():
        for s in range(0, len(gi), batch_size):
            a, b = gi[s:s + batch_size], ti[s:s + batch_size] - window + 1
            win = windows[a, b].to(device)
            est[gi[s:s + batch_size], ti[s:s + batch_size]] = net(win).cpu().numpy()
    return est


if __name__ == "__main__":
    sys.exit(main())
