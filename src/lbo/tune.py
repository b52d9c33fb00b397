"""`python -m lbo.tune`: the paper's hyperparameter search at N=20, as a resumable Optuna study.

    python -m lbo.tune hparams_search=cnn [experiment=quick] [tune.n_trials=40]
    python -m lbo.train -m model=cnn +tuned=cnn window=20,40,60,80

The paper tunes each architecture by grid search at N=20 and reuses the result for N=40..80. Here
a seeded TPE sampler proposes the settings of ``tune.search_space``, a median pruner stops trials
whose validation loss lags after an epoch, and the objective is the best validation loss, the
paper's own criterion; the test set is never touched. The study lives in ``tune.storage``
(SQLite by default, any SQLAlchemy URL for a cluster): a rerun with the same ``tune.study_name``
adds only the missing trials, and several processes on one study share the work. The study is a
parent MLflow run with one child run per trial. The best settings are written to
``tune.handoff`` (``conf/tuned/<model>.yaml``), which training composes with ``+tuned=<model>``.

``tune(cfg)`` is plain Python: it takes a composed ``tune`` config and returns the study's
outcome. ``main`` is the thin Hydra shell around it.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import os
import socket
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import optuna
from hydra.utils import instantiate
from lightning.pytorch.loggers import MLFlowLogger
from omegaconf import DictConfig, OmegaConf, open_dict
from optuna.trial import FrozenTrial, TrialState
from optuna_integration import PyTorchLightningPruningCallback

from lbo.atomic import write_text
from lbo.cli import entry
from lbo.config import require
from lbo.errors import LboError
from lbo.models import model_parameters
from lbo.paths import CONF_DIR
from lbo.tracking import creation_lock, ensure_experiment, sqlite_path
from lbo.train import check, train

#: Trials that count towards ``tune.n_trials``; failed ones (crashes, killed processes) do not.
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
DISTRIBUTIONS = {"float": {"low", "high", "log", "step"}, "int": {"low", "high", "log", "step"},
                 "categorical": {"choices"}}
#: MLflow run status for each final Optuna state; the child run also gets tag ``optuna_state``.
MLFLOW_STATUS = {TrialState.COMPLETE: "FINISHED", TrialState.PRUNED: "KILLED",
                 TrialState.FAIL: "FAILED"}
#: How to install the database drivers that SQLAlchemy asks for.
DRIVERS = {"psycopg": ' (pip install "psycopg[binary]")',
           "psycopg2": " (pip install psycopg2-binary)", "pymysql": " (pip install pymysql)",
           "MySQLdb": " (pip install mysqlclient)"}
PARENT_ATTR = "mlflow_parent_run_id"   # study user attribute: the study's MLflow run
RUN_ATTR = "mlflow_run_id"             # trial user attribute: the trial's MLflow run


# --- the search space -----------------------------------------------------------------------


@dataclass(frozen=True)
class Param:
    """One searched training setting: a dotted config key and its distribution.

    Categorical choices that Optuna cannot store (lists, such as LSTM widths) are offered to it
    as their JSON text and turned back into values by :meth:`decode`.
    """

    key: str
    kind: str
    low: float | int | None = None
    high: float | int | None = None
    log: bool = False
    step: float | int | None = None
    choices: tuple[Any, ...] = ()

    @property
    def labels(self) -> tuple[Any, ...]:
        return tuple(json.dumps(c) if isinstance(c, (list, dict)) else c for c in self.choices)

    def suggest(self, trial: optuna.Trial) -> Any:
        if self.kind == "float":
            return trial.suggest_float(self.key, self.low, self.high, log=self.log, step=self.step)
        if self.kind == "int":
            return trial.suggest_int(self.key, self.low, self.high, log=self.log,
                                     step=self.step or 1)
        return self.decode(trial.suggest_categorical(self.key, self.labels))

    def decode(self, raw: Any) -> Any:
        """A value as Optuna stores it -> the config value."""
        if self.kind == "categorical" and raw in self.labels:
            return self.choices[self.labels.index(raw)]
        return raw


def search_space(cfg: DictConfig) -> list[Param]:
    """``tune.search_space`` as a list of :class:`Param`, checked against the training config
    and the model's parameters; raise :class:`LboError` (one line) for anything wrong."""
    node = cfg.tune.get("search_space")
    raw = OmegaConf.to_container(node, resolve=True) if node is not None else {}
    if not isinstance(raw, dict):
        raise LboError(f"tune.search_space must be a mapping of config keys to distributions, "
                       f"got {raw!r}")
    params: list[Param] = []

    def walk(tree: dict[str, Any], prefix: str) -> None:
        for name, value in tree.items():
            key = f"{prefix}{name}"
            if isinstance(value, dict) and "type" not in value:
                walk(value, f"{key}.")
            else:
                params.append(_param(cfg, key, value))

    walk(raw, "")
    if not params:
        raise LboError("tune.search_space is empty: choose a search with hparams_search=cnn "
                       "or hparams_search=lstm, or declare one under tune.search_space")
    return params


def _param(cfg: DictConfig, key: str, spec: Any) -> Param:
    field = f"tune.search_space.{key}"
    if not isinstance(spec, dict) or spec.get("type") not in DISTRIBUTIONS:
        raise LboError(f"{field} must be {{type: float|int|categorical, ...}}, got {spec!r}")
    kind = spec["type"]
    extra = set(spec) - DISTRIBUTIONS[kind] - {"type"}
    if extra:
        raise LboError(f"{field}: unknown field {sorted(extra)[0]!r} for a {kind} distribution; "
                       f"expected {', '.join(sorted(DISTRIBUTIONS[kind]))}")
    _check_key(cfg, key, field)
    if kind == "categorical":
        choices = spec.get("choices")
        require(isinstance(choices, list) and len(choices) > 0, f"{field}.choices",
                "a non-empty list", choices)
        return Param(key, kind, choices=tuple(choices))
    low, high, log, step = spec.get("low"), spec.get("high"), spec.get("log", False), \
        spec.get("step")
    number = int if kind == "int" else (int, float)
    for name, value in (("low", low), ("high", high)):
        require(isinstance(value, number) and not isinstance(value, bool), f"{field}.{name}",
                f"an {kind}" if kind == "int" else "a number", value)
    require(low <= high, f"{field}.high", f">= low ({low})", high)
    require(isinstance(log, bool), f"{field}.log", "true or false", log)
    require(not log or low > 0, f"{field}.low", "> 0 on a log scale", low)
    require(step is None or (isinstance(step, number) and not isinstance(step, bool)
                             and step > 0 and not log),
            f"{field}.step", "a positive number, and not with log: true", step)
    return Param(key, kind, low, high, log, step)


_MISSING = object()


def _check_key(cfg: DictConfig, key: str, field: str) -> None:
    """The key must name a setting that training reads: a parameter the model accepts, or a
    value already in the training config."""
    if key.startswith("model."):
        name = key[len("model."):]
        accepted = model_parameters(cfg.model.name)
        if name not in accepted:
            raise LboError(f"{field}: {name!r} is not a parameter of model {cfg.model.name!r}; "
                           f"accepted: {', '.join(accepted)}")
        return
    if key.split(".")[0] in ("tune", "hydra", "window", "seed", "data", "data_dir", "output_dir"):
        raise LboError(f"{field}: {key.split('.')[0]!r} is not a hyperparameter; the study "
                       f"searches training settings at a fixed window, seed and data set")
    value = OmegaConf.select(cfg, key, default=_MISSING, throw_on_missing=False)
    if value is _MISSING:
        raise LboError(f"{field}: no key {key!r} in the training config")
    if OmegaConf.is_config(value):
        raise LboError(f"{field}: {key!r} is a group of settings; search its values one by one")


def check_tune(cfg: DictConfig) -> list[Param]:
    """Reject bad study settings with one line naming the field, before any work starts."""
    t = cfg.tune
    require(isinstance(t.n_trials, int) and not isinstance(t.n_trials, bool) and t.n_trials >= 1,
            "tune.n_trials", "an integer >= 1", t.n_trials)
    require(t.timeout is None or (isinstance(t.timeout, (int, float))
                                  and not isinstance(t.timeout, bool) and t.timeout > 0),
            "tune.timeout", "a number of seconds > 0, or null", t.timeout)
    require(isinstance(t.seed, int) and not isinstance(t.seed, bool) and t.seed >= 0,
            "tune.seed", "an integer >= 0", t.seed)
    require(isinstance(t.study_name, str) and t.study_name != "", "tune.study_name",
            "a non-empty string", t.study_name)
    require(isinstance(t.handoff, str) and t.handoff.endswith(".yaml"), "tune.handoff",
            "a path ending in .yaml", t.handoff)
    for key in ("heartbeat_interval", "grace_period", "n_startup_trials"):
        require(isinstance(t[key], int) and not isinstance(t[key], bool) and t[key] >= 1,
                f"tune.{key}", "an integer >= 1", t[key])
    check(cfg)
    return search_space(cfg)


# --- Optuna ---------------------------------------------------------------------------------


class TrialSeededTPESampler(optuna.samplers.BaseSampler):
    """TPE whose random draws for trial n depend only on (seed, n).

    A plain seeded sampler restarts its random stream in every process: a resumed study would
    repeat its first proposals, and workers sharing a study would propose the same ones. Seeding
    per trial keeps a study repeatable and lets any number of processes share it. Each trial
    gets a fresh :class:`optuna.samplers.TPESampler` seeded with (seed, n), through Optuna's
    public sampler interface: TPE keeps no state between trials but its random stream, and
    reads the history from the study.
    """

    def __init__(self, *, seed: int, **kwargs: Any) -> None:
        self.seed, self.tpe_kwargs = seed, kwargs
        self.tpe = self.for_trial(0)

    def for_trial(self, number: int) -> optuna.samplers.TPESampler:
        seed = int(np.random.SeedSequence([self.seed, number]).generate_state(1)[0])
        return optuna.samplers.TPESampler(seed=seed, **self.tpe_kwargs)

    def reseed_rng(self) -> None:  # the per-trial seeds already differ
        return None

    def before_trial(self, study: optuna.Study, trial: FrozenTrial) -> None:
        self.tpe = self.for_trial(trial.number)
        self.tpe.before_trial(study, trial)

    def infer_relative_search_space(self, study, trial):
        return self.tpe.infer_relative_search_space(study, trial)

    def sample_relative(self, study, trial, search_space):
        return self.tpe.sample_relative(study, trial, search_space)

    def sample_independent(self, study, trial, param_name, param_distribution):
        return self.tpe.sample_independent(study, trial, param_name, param_distribution)

    def after_trial(self, study, trial, state, values) -> None:
        self.tpe.after_trial(study, trial, state, values)


def make_pruner(node: DictConfig) -> optuna.pruners.BasePruner:
    """``tune.pruner`` (a ``_target_`` config, MedianPruner by default) as a pruner."""
    try:
        pruner = instantiate(node)
    except Exception as e:
        cause = e.__cause__ or e
        reason = " ".join(str(cause).split())[:300]
        raise LboError(f"tune.pruner: cannot build {node.get('_target_')!r} "
                       f"({type(cause).__name__}: {reason})") from e
    if not isinstance(pruner, optuna.pruners.BasePruner):
        raise LboError(f"tune.pruner must build an optuna pruner, got {type(pruner).__name__}")
    return pruner


def redact(url: str) -> str:
    """The storage URL as it may be printed and logged: without its password."""
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception as e:  # sqlalchemy.exc.ArgumentError
        raise LboError(f"tune.storage: {url!r} is not a database URL "
                       f"(sqlite:///path/optuna.db or postgresql://user:pass@host/db)") from e


def open_storage(url: str, heartbeat_interval: int,
                 grace_period: int) -> optuna.storages.RDBStorage:
    """Connect to (and if new, initialise) the study database; one line if it cannot.

    A trial whose process stops sending heartbeats for ``grace_period`` s (killed, preempted)
    is marked failed and queued once more with the same parameters.
    """
    from sqlalchemy.engine import make_url

    shown = redact(url)
    backend = make_url(url).get_backend_name()
    engine_kwargs: dict[str, Any] = {}
    if backend == "sqlite":
        # workers on one SQLite file wait for each other's writes instead of failing at once
        engine_kwargs = {"connect_args": {"timeout": 60}}
    elif backend == "postgresql":
        engine_kwargs = {"connect_args": {"connect_timeout": 10}, "pool_pre_ping": True}
    try:
        with creation_lock(url), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # heartbeats are marked experimental
            return optuna.storages.RDBStorage(
                url, engine_kwargs=engine_kwargs, heartbeat_interval=heartbeat_interval,
                grace_period=grace_period,
                heartbeat_stale_trial_callback=optuna.storages.RetryFailedTrialCallback(
                    max_retry=1))
    except ImportError as e:  # optuna wraps the driver's ModuleNotFoundError
        missing = getattr(e.__cause__, "name", None) or getattr(e, "name", None) or "?"
        hint = DRIVERS.get(missing, "")
        raise LboError(f"tune.storage: cannot open {shown}: its database driver {missing!r} "
                       f"is not installed{hint}") from e
    except Exception as e:
        reason = (str(getattr(e, "orig", None) or e).strip().splitlines() or [""])[0]
        raise LboError(f"tune.storage: cannot open {shown} ({type(e).__name__}: {reason})") \
            from e


class ClaimLock:
    """A lock, shared by every worker of one study, held from "is a trial still needed?" until
    that trial is RUNNING in the storage, so that workers together start exactly
    ``tune.n_trials`` trials.

    PostgreSQL: a session advisory lock on a connection of its own, which the server drops
    when a killed worker's connection goes. SQLite (one machine): a file lock. Other
    databases: none, and each extra worker may add one trial.
    """

    def __init__(self, storage: optuna.storages.RDBStorage, url: str, study: str) -> None:
        from sqlalchemy.engine import make_url

        self.backend = make_url(url).get_backend_name()
        digest = hashlib.sha1(f"lbo-tune:{study}".encode()).digest()
        self.key = int.from_bytes(digest[:8], "big", signed=True)
        self.engine = storage.engine
        self.file = None
        db = sqlite_path(url) if self.backend == "sqlite" else None
        if db is not None and db.parent.is_dir():  # beside the database, one per study
            from filelock import FileLock

            self.file = FileLock(db.with_name(f"{db.name}.{digest.hex()[:12]}.lock"))
        self.conn = None

    def acquire(self) -> None:
        from sqlalchemy import text

        if self.file is not None:
            self.file.acquire()
        elif self.backend == "postgresql":
            self.conn = self.engine.connect()
            self.conn.execute(text("SELECT pg_advisory_lock(:k)"), {"k": self.key})

    def release(self) -> None:
        """Idempotent: the objective releases it as its trial starts, the loop once more."""
        from sqlalchemy import text

        if self.file is not None and self.file.is_locked:
            self.file.release()
        if self.conn is not None:
            try:
                self.conn.execute(text("SELECT pg_advisory_unlock(:k)"), {"k": self.key})
            finally:
                self.conn.close()
                self.conn = None


def needs_trial(study: optuna.Study, n_trials: int) -> bool:
    """Whether the study needs another trial: fewer than ``n_trials`` finished or running.

    Trials whose worker went silent are failed first (and queued again once, with their
    parameters, for the next ``ask``), so a killed worker's trial does not count as running.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fail_stale_trials is marked experimental
        optuna.storages.fail_stale_trials(study)
    busy = study.get_trials(deepcopy=False, states=(*FINISHED, TrialState.RUNNING))
    return len(busy) < n_trials


def _describe(trial: FrozenTrial, space: list[Param]) -> str:
    params = " ".join(f"{p.key}={_short(p.decode(trial.params[p.key]))}" for p in space
                      if p.key in trial.params)
    seconds = trial.duration.total_seconds() if trial.duration else float("nan")
    if trial.state == TrialState.COMPLETE:
        outcome = f"val_loss {trial.value:.6g}"
    elif trial.state == TrialState.PRUNED:
        steps = trial.intermediate_values
        outcome = f"pruned after epoch {max(steps)}" if steps else "pruned"
    else:
        outcome = trial.state.name.lower()
    return f"trial {trial.number:3d}  {outcome:<26s} {seconds:7.1f} s  {params}"


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return json.dumps(value, separators=(",", ":")) if isinstance(value, list) else str(value)


# --- MLflow ---------------------------------------------------------------------------------


class StudyRun:
    """The study's parent MLflow run, found again through the study on a rerun, so that a
    resumed or shared study keeps one parent. Child runs are the trials' training runs."""

    def __init__(self, cfg: DictConfig, study: optuna.Study, storage: str) -> None:

        log = cfg.logger
        self.client, exp_id = ensure_experiment(log.tracking_uri, log.experiment_name,
                                                log.artifact_location)
        self.run_id = study.user_attrs.get(PARENT_ATTR)
        if self._status(self.run_id) is not None:
            self.client.update_run(self.run_id, status="RUNNING")
            return
        name = study.study_name
        own = self.client.create_run(exp_id, run_name=f"study-{name}", tags={
            "optuna_study": name, "optuna_storage": storage, "optuna_role": "study",
            "model": cfg.model.name, "window": str(cfg.window), "data": cfg.data.name}).info
        self.run_id = self._first(exp_id, name, storage, own)
        if self.run_id != own.run_id:  # a worker that started with this one was first
            self.client.delete_run(own.run_id)
            return
        study.set_user_attr(PARENT_ATTR, self.run_id)
        for key, value in {"study_name": name, "storage": storage, "model": cfg.model.name,
                           "window": cfg.window, "data": cfg.data.name, "sampler": "TPE",
                           "sampler_seed": cfg.tune.seed,
                           "pruner": cfg.tune.pruner.get("_target_", "")}.items():
            self.client.log_param(self.run_id, key, value)
        self.client.log_text(self.run_id, OmegaConf.to_yaml(cfg.tune.search_space),
                             "search_space.yaml")

    def _first(self, exp_id: str, name: str, storage: str, own: Any) -> str:
        """Workers started together each open a parent before any has saved its id in the
        study; all of them keep the earliest, whichever of them looks last."""
        found = self.client.search_runs(
            [exp_id], "tags.optuna_role = 'study' and attributes.status = 'RUNNING' and "
            f"attributes.start_time >= {own.start_time - 600_000}", max_results=1000)
        same = [r.info for r in found if r.data.tags.get("optuna_study") == name
                and r.data.tags.get("optuna_storage") == storage]
        return min([*same, own], key=lambda i: (i.start_time, i.run_id)).run_id

    def _status(self, run_id: str | None) -> str | None:
        """The run's status, or None when this tracking store has no such live run."""
        from mlflow.exceptions import MlflowException

        try:
            info = self.client.get_run(run_id).info if run_id else None
        except MlflowException:
            return None
        return info.status if info is not None and info.lifecycle_stage == "active" else None

    def mark(self, trial: FrozenTrial) -> None:
        """Close the trial's run with its final Optuna state; log a completed one's loss here."""
        epochs = trial.intermediate_values
        self.close_trial(trial.user_attrs.get(RUN_ATTR), trial.state,
                         max(epochs) if trial.state == TrialState.PRUNED and epochs else None)
        if trial.state == TrialState.COMPLETE:
            self.client.log_metric(self.run_id, "trial_val_loss", trial.value, step=trial.number)

    def close_trial(self, run_id: str | None, state: TrialState,
                    pruned_epoch: int | None = None) -> None:
        if run_id is None or state not in MLFLOW_STATUS:
            return
        self.client.set_tag(run_id, "optuna_state", state.name)
        if pruned_epoch is not None:
            self.client.set_tag(run_id, "optuna_pruned_epoch", str(pruned_epoch))
        self.client.set_terminated(run_id, MLFLOW_STATUS[state])

    def close_stale(self, study: optuna.Study) -> None:
        """Trials failed for a silent heartbeat left their runs RUNNING: close them FAILED."""
        for trial in study.get_trials(deepcopy=False, states=(TrialState.FAIL,)):
            if self._status(trial.user_attrs.get(RUN_ATTR)) == "RUNNING":
                self.mark(trial)

    def summarise(self, study: optuna.Study, space: list[Param], handoff: Path | None,
                  status: str) -> None:
        counts = {s: len(study.get_trials(deepcopy=False, states=(s,))) for s in TrialState}
        finished = counts[TrialState.COMPLETE] + counts[TrialState.PRUNED]
        for state in (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL):
            self.client.log_metric(self.run_id, f"n_{state.name.lower()}", counts[state],
                                   step=finished)
        if counts[TrialState.COMPLETE]:
            best = study.best_trial
            self.client.log_metric(self.run_id, "best_val_loss", best.value, step=finished)
            self.client.set_tag(self.run_id, "best_trial", str(best.number))
            # tags, not params: a resumed study may find a better trial, and MLflow params
            # cannot change once logged
            for p in space:
                if p.key in best.params:
                    self.client.set_tag(self.run_id, f"best.{p.key}",
                                        str(p.decode(best.params[p.key])))
            with tempfile.TemporaryDirectory() as tmp:
                for png in _figures(study, Path(tmp)):
                    self.client.log_artifact(self.run_id, str(png))
        if handoff is not None:
            self.client.log_artifact(self.run_id, str(handoff), artifact_path="tuned")
        self.client.set_terminated(self.run_id, status)


def _figures(study: optuna.Study, folder: Path) -> list[Path]:
    """The optimisation history and the trials' validation curves, as PNGs."""
    import matplotlib.pyplot as plt
    from optuna.visualization import matplotlib as ovm

    from lbo import plots

    out = []
    # optuna's plots switch the global style to ggplot: keep that to these two figures
    with warnings.catch_warnings(), plt.rc_context():
        warnings.simplefilter("ignore")  # optuna marks its matplotlib plots experimental
        for name, plot in (("optimization_history", ovm.plot_optimization_history),
                           ("intermediate_values", ovm.plot_intermediate_values)):
            ax = plot(study)
            out.append(plots.save(ax.figure, folder / f"{name}.png"))
    return out


# --- trials ---------------------------------------------------------------------------------


class Pruning(PyTorchLightningPruningCallback):
    """Optuna's Lightning pruning callback (reports ``val_loss`` after each validation epoch,
    raises :class:`optuna.TrialPruned`), which also records the trial's MLflow run."""

    def __init__(self, trial: optuna.Trial) -> None:
        super().__init__(trial, monitor="val_loss")
        self.optuna_trial = trial  # our own reference, not the parent's private attribute

    def on_fit_start(self, trainer, pl_module) -> None:
        super().on_fit_start(trainer, pl_module)
        if isinstance(trainer.logger, MLFlowLogger):
            self.optuna_trial.set_user_attr(RUN_ATTR, trainer.logger.run_id)


def trial_config(cfg: DictConfig, values: dict[str, Any], number: int, study_name: str,
                 output_dir: Path) -> DictConfig:
    """The training config of one trial: ``cfg`` with the sampled values, its own output folder,
    and nothing that reads the test set."""
    out = copy.deepcopy(cfg)
    with open_dict(out):
        for key, value in values.items():
            OmegaConf.update(out, key, value, merge=False)
        out.output_dir = str(output_dir / f"trial_{number:03d}")
        del out.tune
        callbacks = out.get("callbacks") or {}
        for name in list(callbacks):
            target = str(callbacks[name].get("_target_", ""))
            # Tuning must never see the test set: the evaluation callback scores the test grid
            # at the end of fit, so it is left out of every trial. Progress bars would bury the
            # one line per trial.
            if target == "lbo.callbacks.Evaluation" or target.endswith("ProgressBar"):
                del callbacks[name]
        out.trainer.enable_progress_bar = False
        out.trainer.enable_model_summary = False
        if out.get("logger"):
            out.logger.run_name = f"{study_name}-trial{number}"
    return out


# --- the study ------------------------------------------------------------------------------


def tune(cfg: DictConfig) -> dict[str, Any]:
    """Run (or resume, or join) the study described by ``cfg.tune``; write the hand-off config.

    Parameters
    ----------
    cfg : a composed ``tune`` config (the training config plus ``tune``).

    Returns
    -------
    ``study_name``, ``storage``, ``best_value``, ``best_params`` (config key -> value),
    ``best_trial``, ``new_trials`` (numbers of the trials this call ran), ``n_complete``,
    ``n_pruned``, ``n_failed``, ``handoff`` (path), ``train_command``, ``parent_run_id``.

    Raises
    ------
    LboError
        For bad settings (before any trial), or when the study has no completed trial.
    """
    space = check_tune(cfg)
    t = cfg.tune
    pruner = make_pruner(t.pruner)
    storage = open_storage(t.storage, t.heartbeat_interval, t.grace_period)
    shown = redact(t.storage)
    sampler = TrialSeededTPESampler(seed=t.seed, n_startup_trials=t.n_startup_trials)
    study = optuna.create_study(study_name=t.study_name, storage=storage, sampler=sampler,
                                pruner=pruner, direction="minimize", load_if_exists=True)
    for key, value in (("model", cfg.model.name), ("window", cfg.window),
                       ("data", cfg.data.name)):
        study.set_user_attr(key, value)
    output = Path(cfg.output_dir)
    tracking = cfg.get("logger") and str(cfg.logger.get("_target_", "")).endswith("MLFlowLogger")
    run = StudyRun(cfg, study, shown) if tracking else None

    finished = len(study.get_trials(deepcopy=False, states=FINISHED))
    remaining = t.n_trials - finished
    print(f"study {t.study_name} in {shown}: {finished} of {t.n_trials} trials finished"
          + (f", running {remaining} more" if remaining > 0 else ""), flush=True)
    new: list[int] = []

    claim = ClaimLock(storage, t.storage, t.study_name)

    def objective(trial: optuna.Trial) -> float:
        claim.release()  # the trial is RUNNING in the storage: other workers count it now
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        values = {p.key: p.suggest(trial) for p in space}
        trial_cfg = trial_config(cfg, values, trial.number, t.study_name, output)
        trial.set_user_attr("output_dir", trial_cfg.output_dir)
        tags = {"optuna_study": t.study_name, "optuna_trial": str(trial.number)}
        if run is not None:
            tags["mlflow.parentRunId"] = run.run_id
        try:
            return train(trial_cfg, callbacks=[Pruning(trial)], tags=tags)["val_loss"]
        except optuna.TrialPruned:
            raise
        except BaseException:
            # Optuna re-raises the error without calling the study callbacks: close the run here
            if run is not None:
                run.close_trial(trial.user_attrs.get(RUN_ATTR), TrialState.FAIL)
            raise

    def progress(study: optuna.Study, trial: FrozenTrial) -> None:
        new.append(trial.number)
        if run is not None:
            run.mark(trial)
        print(_describe(trial, space), flush=True)

    status = "FINISHED"
    try:
        # one trial at a time, each claimed under the study's lock: workers sharing the
        # study stop once it holds n_trials finished (or running) trials, and never overshoot
        start = time.monotonic()
        while t.timeout is None or time.monotonic() - start < t.timeout:
            claim.acquire()
            try:
                if not needs_trial(study, t.n_trials):
                    break
                study.optimize(objective, n_trials=1, callbacks=[progress])
            finally:
                claim.release()
    except KeyboardInterrupt:
        status = "KILLED"
        raise
    except BaseException:
        status = "FAILED"
        raise
    finally:
        handoff = None
        if status == "FINISHED" and _completed(study):
            handoff = write_handoff(cfg, study, space, shown)
        if run is not None:
            run.close_stale(study)
            run.summarise(study, space, handoff, status)

    counts = {s: len(study.get_trials(deepcopy=False, states=(s,))) for s in TrialState}
    if handoff is None:
        raise LboError(f"study {t.study_name}: no trial has completed "
                       f"({counts[TrialState.PRUNED]} pruned, {counts[TrialState.FAIL]} failed),"
                       f" so no hand-off was written; rerun with a larger tune.n_trials")
    best = study.best_trial
    command = train_command(cfg.model.name, handoff)
    params = {p.key: p.decode(best.params[p.key]) for p in space if p.key in best.params}
    print(f"best: trial {best.number}, val_loss {best.value:.6g}: "
          + " ".join(f"{k}={_short(v)}" for k, v in params.items()))
    print(f"train with: {command}")
    print(f"tuned: {handoff}", flush=True)
    return {"study_name": t.study_name, "storage": shown, "best_value": best.value,
            "best_params": params, "best_trial": best.number, "new_trials": new,
            "n_complete": counts[TrialState.COMPLETE], "n_pruned": counts[TrialState.PRUNED],
            "n_failed": counts[TrialState.FAIL], "handoff": handoff, "train_command": command,
            "parent_run_id": run.run_id if run is not None else None}


def _completed(study: optuna.Study) -> bool:
    return bool(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))


def write_handoff(cfg: DictConfig, study: optuna.Study, space: list[Param],
                  storage: str) -> Path:
    """Write the best trial's settings as a ``# @package _global_`` config (atomically)."""
    best = study.best_trial
    values = OmegaConf.create({})
    for p in space:
        if p.key in best.params:
            OmegaConf.update(values, p.key, p.decode(best.params[p.key]), merge=True)
    path = Path(cfg.tune.handoff)
    header = (
        "# @package _global_\n"
        f"# Written by `python -m lbo.tune`: the best of study {study.study_name!r} in "
        f"{storage}\n"
        f"# (model {cfg.model.name}, window {cfg.window}, data {cfg.data.name}; trial "
        f"{best.number}, val_loss {best.value:.6g}).\n"
        f"# Use: {train_command(cfg.model.name, path)}\n")
    return write_text(path, header + OmegaConf.to_yaml(values))


def train_command(model: str, handoff: Path) -> str:
    """The training line that composes ``handoff``: ``+<folder>=<name>``, with a search path
    when the folder is not under conf/."""
    handoff = Path(handoff).resolve()
    command = (f"python -m lbo.train -m model={model} +{handoff.parent.name}={handoff.stem} "
               f"window=20,40,60,80")
    if handoff.parent.parent != CONF_DIR.resolve():
        command += f" 'hydra.searchpath=[file://{handoff.parent.parent}]'"
    return command


def quiet() -> None:
    """One line per trial from :func:`tune` instead of Optuna's and Lightning's own chatter."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)


def _quiet_tune(cfg: DictConfig) -> float:
    quiet()
    return tune(cfg)["best_value"]


main = entry("tune", _quiet_tune)


if __name__ == "__main__":
    sys.exit(main())
