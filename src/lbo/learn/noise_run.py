"""A classical filter's noise as a tracked, trainable observer: ``lbo.train model=gyro_ekf``.

    python -m lbo.train model=gyro_ekf data=hill [model.objective=innovations]
    python -m lbo.train model=gyro_ekf data=logs data.train=[...] data.val=[...] data.test=[...]

The gyro EKF (:mod:`lbo.filters.gyro`) has seven noises and no weights. :func:`train` learns
them on a vehicle's logs as :mod:`lbo.learn.gyro_fit` does (``model.objective=truth``: the
estimates' error against the truth; ``innovations``: the fixes' likelihood under the filter's
own prediction, the truth columns dropped unread), keeps the epoch best on the validation
logs, scores the test logs (each log's measure against the kinematic EKF, their mean and the
worst, beside the gyro EKF with its default noise) and logs it all as one MLflow run, as
every learned observer is:

- params (the resolved config), tags (``model=gyro_ekf``, ``data``, ``config_hash``, ...),
  ``train_loss`` and ``val_loss`` per epoch, ``test_vs_ekf_<log>``, ``test_vs_ekf_mean`` and
  ``test_vs_ekf_worst`` (``test_defaults_vs_ekf_*``: the default noise's);
- artifacts ``gyro_ekf/gyro_noise.json`` (the noise kept), ``gyro_ekf/conditions.json``
  (the vehicle and the classical noise preset it was learned with), ``gyro_ekf/history.csv``,
  ``gyro_ekf/test.md`` and ``config.yaml``.

``lbo.observe observer=<run id>`` (and :meth:`lbo.Observer.load`) runs the gyro EKF with that
noise (:func:`lbo.tracking.artifacts.learned_noise`). The same files are written to the run's
``output_dir``. With ``resume=true`` a finished run of the same config is reused.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from lbo.core.atomic import write_text
from lbo.core.checks import require
from lbo.core.errors import LboError
from lbo.core.redact import scrub
from lbo.filters.gyro_noise import GyroNoise
from lbo.learn.gyro_fit import GyroFit, Settings
from lbo.logs.sets import LogSpec, is_logs, spec_from_cfg
from lbo.sim.columns import STATE

__all__ = ["ACROSS", "FOLDER", "NAME", "across_drives", "check", "train"]

NAME = "gyro_ekf"
"""``model.name`` of the gyro EKF learned as an observer."""
FOLDER = "gyro_ekf"
"""The run's artifact folder holding what :func:`lbo.tracking.artifacts.learned_noise` reads."""
LEARNED = "gyro, learned noise"
DEFAULTS = "gyro, receiver's accuracy and velocity"  # lbo.scoring.receiver.score's label
ACROSS = "gyro, noise learned on the other drives"
"""The row of a leave-one-drive-out table (:func:`across_drives`) whose noise was learned on
every drive but the one scored."""


def check(cfg: DictConfig) -> tuple[Settings, LogSpec]:
    """The run's settings and logs, checked before any work (one line naming the field)."""
    settings = Settings.from_cfg(cfg.model, "model")
    require(isinstance(cfg.model.get("across_drives", False), bool), "model.across_drives",
            "true or false", cfg.model.get("across_drives"))
    if not is_logs(cfg):
        raise LboError(f"data: model=gyro_ekf learns from a vehicle's logs (data=logs with "
                       f"data.train and data.val, or data=hill); got data={cfg.data.name}")
    if settings.epochs < 1:
        raise LboError(f"model.epochs: expected an integer >= 1 (the fit's steps), got "
                       f"{settings.epochs}")
    spec = spec_from_cfg(cfg, need=("train", "val"))
    logger = cfg.get("logger")
    if logger and logger.get("tracking_uri"):
        from lbo.tracking.runs import check_store

        check_store(logger.tracking_uri)
    return settings, spec


def read(spec: LogSpec, part: str, truth: bool) -> list[pd.DataFrame]:
    """The logs of set ``part`` as :func:`lbo.learn.gyro_fit.fit` takes them, each read and
    checked as ``lbo.observe`` reads a log; without ``truth`` its truth columns dropped."""
    from lbo.logs.io import check_log, read_log

    out = []
    for path in spec.files[part]:
        where = f"data.{part}: {path}"
        df, _ = spec.log_format.apply(read_log(path), where)
        has_truth = check_log(df, where, spec.log_format.heading)
        if truth and not has_truth:
            raise LboError(f"{where}: no truth columns x, y, psi (model.objective=truth "
                           "learns from them; model.objective=innovations does without)")
        out.append(df if truth else df.drop(columns=list(STATE), errors="ignore"))
    return out


def score(logs: list[pd.DataFrame], names: list[str], noise: GyroNoise, spec: LogSpec
          ) -> pd.DataFrame:
    """Each test log's measure against the kinematic EKF (:func:`lbo.scoring.receiver.
    ratio_to`) for the learned noise and the defaults: one row per log and estimator
    (``log, estimator, x_m, y_m, psi_mrad, rows, vs_ekf``)."""
    from lbo.scoring.receiver import EKF, ratio_to
    from lbo.scoring.receiver import score as score_log

    tables = []
    for name, log in zip(names, logs):
        table, _ = score_log(log, ["ekf", "gyro"], spec.vehicle, spec.noise, {LEARNED: noise})
        table["vs_ekf"] = ratio_to(table, EKF)
        table.insert(0, "log", name)
        tables.append(table)
    return pd.concat(tables, ignore_index=True)


def across_drives(drives: list[pd.DataFrame], settings: Settings, vehicle: Any, noise: Any,
                  observers: list[str], out: Path | None = None,
                  progress: Callable[[str], None] | None = print,
                  nets: Callable[[int, list[pd.DataFrame]], Mapping[str, Any]] | None = None,
                  held_out: bool = False) -> pd.DataFrame:
    """Leave-one-drive-out (:func:`lbo.scoring.drives.leave_one_out`): for each drive (a log
    with truth), the gyro EKF's noise learned from the defaults on all the others as
    ``settings`` says (none with 0 epochs; by the innovations their truth is not read), the
    epoch kept by those same drives, or with ``held_out`` learned on all of them but the last
    and kept by the last (:func:`lbo.scoring.drives.kept_apart`); it, ``observers`` and the
    learned observers ``nets(k, train)`` gives for the fold (by row label) scored on the one
    left out. With ``out``, each fold's noise is written as
    ``gyro_noise_without_drive<k>.json``. Returns the long table (one row per drive and
    estimator, ``vs_ekf``)."""
    from lbo.learn import gyro_fit
    from lbo.scoring import drives as across

    R, start = gyro_fit.fix_cov(noise), settings.start(noise.Q)

    def learn(k: int, train: list[pd.DataFrame]) -> across.Fold:
        noises = {}
        if settings.epochs:
            fit_on, keep_by = across.kept_apart(train) if held_out else (train, train)
            fitted = gyro_fit.fit(fit_on, keep_by, vehicle, R, start, progress=None,
                                  **settings.kwargs(vehicle.dt))
            if out is not None:
                fitted.noise.save(out / f"gyro_noise_without_drive{k + 1}.json")
            noises[ACROSS] = fitted.noise
        return across.Fold(noises, nets(k, train) if nets is not None else {})

    return across.leave_one_out(drives, learn, observers, vehicle, noise, progress=progress)


def test_metrics(table: pd.DataFrame) -> dict[str, float]:
    """``test_vs_ekf_<log>``, ``_mean`` and ``_worst`` of the learned noise, and
    ``test_defaults_vs_ekf_mean`` and ``_worst`` of the default one."""
    out: dict[str, float] = {}
    for label, prefix in ((LEARNED, "test_vs_ekf"), (DEFAULTS, "test_defaults_vs_ekf")):
        rows = table[table["estimator"] == label]
        ratios = rows["vs_ekf"].to_numpy(float)
        if label == LEARNED:
            out |= {f"{prefix}_{name}": float(v) for name, v in zip(rows["log"], ratios)}
        out |= {f"{prefix}_mean": float(ratios.mean()), f"{prefix}_worst": float(ratios.max())}
    return out


def markdown(table: pd.DataFrame) -> str:
    """The test table: each log's measure against the EKF (x, y m; psi mrad; ratio)."""
    lines = ["| log | estimator | x (m) | y (m) | psi (mrad) | vs EKF |",
             "|---|---|---:|---:|---:|---:|"]
    for _, r in table.iterrows():
        lines.append(f"| {r['log']} | {r['estimator']} | {r['x_m']:.3f} | {r['y_m']:.3f} | "
                     f"{r['psi_mrad']:.2f} | {r['vs_ekf']:.3f} |")
    return "\n".join(lines) + "\n"


def train(cfg: DictConfig, params: dict[str, Any], tags: dict[str, str]) -> dict[str, Any]:
    """Learn the gyro EKF's noise as ``cfg`` says and log it as an MLflow run.

    params : the run's flat params (the resolved config); tags : its tags besides lbo's.

    Returns ``name``, ``val_loss`` (the kept epoch's validation value), ``run_id`` (None
    without a logger), ``checkpoint`` (the noise's JSON), ``epochs``, ``reused`` and the test
    metrics (:func:`test_metrics`)."""
    from lbo.core.runfolder import claim
    from lbo.learn import gyro_fit
    from lbo.learn.identity import config_hash, run_tags
    from lbo.learn.resume import prior_runs

    settings, spec = check(cfg)
    digest = config_hash(cfg)
    if cfg.get("resume") and cfg.get("logger"):
        reused, _ = prior_runs(cfg, digest)
        if reused is not None:
            print(f"reusing finished run {reused['run_id']} ({NAME}, same config)")
            artifacts = reused["checkpoint"].removesuffix("/checkpoints/best.ckpt")
            return {**reused, "name": NAME, "checkpoint": f"{artifacts}/{FOLDER}/gyro_noise.json"}
    truth = settings.objective == "truth"
    train_logs, val_logs = read(spec, "train", truth), read(spec, "val", truth)
    tests = read(spec, "test", True) if spec.files["test"] else []
    start = settings.start(spec.noise.Q)
    out = Path(cfg.output_dir)
    with claim(out):
        run = _Run.open(cfg, {**tags, **run_tags(digest)}, params)
        try:
            how = "its truth" if truth else "its fixes' likelihood, no truth read"
            if settings.receiver_noise == "variogram":
                how += ", the receiver's noise by its variogram"
            if settings.hold:
                how += f", {', '.join(settings.hold)} held"
            print(f"learning the gyro EKF's noise on {len(train_logs)} log(s) of {spec.name} "
                  f"by {how} ({settings.epochs} epochs, {settings.method}); the best on "
                  f"{len(val_logs)} validation log(s) is kept")
            fitted = gyro_fit.fit(train_logs, val_logs, spec.vehicle, gyro_fit.fix_cov(spec.noise),
                                  start, progress=lambda line: print("  " + line),
                                  **settings.kwargs(spec.vehicle.dt))
            print(f"  kept epoch {fitted.best_epoch}: {fitted.noise}")
            table = (score(tests, [p.stem for p in spec.files["test"]], fitted.noise, spec)
                     if tests else None)
            files = _write(out, cfg, fitted, spec, table)
            metrics = test_metrics(table) if table is not None else {}
            if cfg.model.get("across_drives"):  # every drive scored: each with its truth
                scored = ((train_logs + val_logs) if truth
                          else read(spec, "train", True) + read(spec, "val", True))
                drives, wide = _across(spec, settings, out, scored + tests)
                metrics |= drives
                files["drives.md"] = wide
            run.finish(fitted, metrics, files)
        except BaseException:
            run.fail()
            raise
    if table is not None:
        print(f"test logs (measure against the kinematic EKF):\n{markdown(table)}", end="")
    val = fitted.history["val"].to_numpy(float)
    return {"name": NAME, "val_loss": float(val[fitted.best_epoch]), "run_id": run.run_id,
            "checkpoint": str(files["gyro_noise.json"]), "epochs": settings.epochs,
            "reused": False, **metrics}


def _across(spec: LogSpec, settings: Settings, out: Path, logs: list[pd.DataFrame]
            ) -> tuple[dict[str, float], Path]:
    """``model.across_drives``: every log of the three sets a drive, each scored by the noise
    learned on the others (:func:`across_drives`); its metrics ``drives_vs_ekf_<log>``,
    ``_mean`` and ``_worst``, and ``drives.md``. ``logs``: the sets' logs in that order, each
    with its truth (those already read, not read again)."""
    from lbo.scoring import drives as across

    names = [p.stem for part in ("train", "val", "test") for p in spec.files[part]]
    if len(names) < 2:
        raise LboError(f"model.across_drives: leave-one-drive-out needs two logs or more in "
                       f"data.train, data.val and data.test together, got {len(names)}")
    print(f"leave-one-drive-out over {len(logs)} drives ({', '.join(names)}): the noise "
          "learned on the others, scored on each")
    table = across_drives(logs, settings, spec.vehicle, spec.noise, ["ekf", "gyro"], out,
                          progress=lambda line: print("  " + line))
    wide = across.summary(table)
    print(across.markdown(wide), end="")
    row = wide[wide["estimator"] == ACROSS].iloc[0]
    metrics = {f"drives_vs_ekf_{name}": float(row[f"drive {k + 1}"])
               for k, name in enumerate(names)}
    metrics |= {"drives_vs_ekf_mean": float(row["mean"]),
                "drives_vs_ekf_worst": float(row["worst"])}
    return metrics, write_text(out / "drives.md", across.markdown(wide))


def _write(out: Path, cfg: DictConfig, fitted: GyroFit, spec: LogSpec,
           table: pd.DataFrame | None) -> dict[str, Path]:
    """The run's files in ``out``, each atomic, by artifact name."""
    from lbo.logs.io import write_table

    files = {"gyro_noise.json": out / "gyro_noise.json",
             "conditions.json": write_text(out / "conditions.json", json.dumps(
                 {"vehicle": spec.vehicle.__dict__,
                  "noise": {"process_sigma": list(spec.noise.process_sigma),
                            "measurement_sigma": list(spec.noise.measurement_sigma),
                            "name": spec.noise.name}}, indent=1) + "\n"),
             "history.csv": write_table(fitted.history, out / "history.csv"),
             "config.yaml": write_text(out / "config.yaml",
                                       scrub(OmegaConf.to_yaml(cfg, resolve=True)))}
    fitted.noise.save(files["gyro_noise.json"])
    if table is not None:
        files["test.md"] = write_text(out / "test.md", markdown(table))
        files["test.csv"] = write_table(table, out / "test.csv")
    return files


class _Run:
    """The MLflow run of one fit (or none, with ``logger=null``)."""

    def __init__(self, client: Any = None, run_id: str | None = None) -> None:
        self.client, self.run_id = client, run_id

    @classmethod
    def open(cls, cfg: DictConfig, tags: dict[str, str], params: dict[str, Any]) -> _Run:
        logger = cfg.get("logger")
        if not logger:
            return cls()
        from mlflow.entities import Param

        from lbo.tracking.runs import logger_experiment

        client, exp = logger_experiment(logger)
        run_id = client.create_run(exp, run_name=NAME, tags=tags).info.run_id
        items = [Param(k, str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):  # MLflow takes at most 100 params a call
            client.log_batch(run_id, params=items[i:i + 100])
        return cls(client, run_id)

    def finish(self, fitted: GyroFit, metrics: dict[str, float], files: dict[str, Path]
               ) -> None:
        if self.run_id is None:
            return
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        rows: list[Metric] = []
        for _, h in fitted.history.iterrows():
            step = int(h["epoch"])
            rows += [Metric("train_loss", float(h["loss"]), now, step),
                     Metric("val_loss", float(h["val"]), now, step)]
        rows += [Metric(k, v, now, 0) for k, v in metrics.items() if np.isfinite(v)]
        log: Callable[..., None] = self.client.log_batch
        for i in range(0, len(rows), 1000):
            log(self.run_id, metrics=rows[i:i + 1000])
        for name, path in files.items():
            self.client.log_artifact(self.run_id, str(path),
                                     artifact_path=None if name == "config.yaml" else FOLDER)
        self.client.set_terminated(self.run_id, "FINISHED")

    def fail(self) -> None:
        if self.run_id is not None:
            self.client.set_terminated(self.run_id, "FAILED")
