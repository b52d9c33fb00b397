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
``tune.handoff`` (``conf/tuned/<model>.yaml``), which training composes with ``+tuned=<model>``:
those of the best completed trial inside the current search space (a note names a better one
outside a since narrowed range). Ctrl-C fails the running trial, closes its run FAILED and the
study's KILLED; the same command then finishes the study. A resumed study whose stored
categorical choices (or a parameter's kind or log scale) the search space no longer matches is
refused before any trial.

``tune(cfg)`` is plain Python: it takes a composed ``tune`` config and returns the study's
outcome. ``main`` is the thin Hydra shell around it. The parts live beside it: the search
space, the sampler and the pruner in :mod:`lbo.tuning.search`, the hand-off in
:mod:`lbo.tuning.handoff`, the database and the claim lock in
:mod:`lbo.tuning.storage`, the MLflow runs and figures in :mod:`lbo.tuning.mirror`.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import re
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import optuna
from omegaconf import DictConfig, OmegaConf, open_dict
from optuna.trial import FrozenTrial, TrialState

from lbo.core.checks import integer, number, require
from lbo.core.cli import entry
from lbo.core.errors import LboError, TrainingDiverged
from lbo.train import SLIP, check, train
from lbo.tuning.handoff import (
    best_trials,
    hydra_searchpath,
    outside_note,
    outside_space,
    train_command,
    write_handoff,
)
from lbo.tuning.mirror import RUN_ATTR, StudyRun
from lbo.tuning.search import (
    Param,
    TrialSeededTPESampler,
    check_resumed,
    make_pruner,
    search_space,
    short_value,
)
from lbo.tuning.storage import (
    FINISHED,
    ClaimLock,
    close_storage,
    fail_own_trials,
    needs_trial,
    open_storage,
    redact,
    worker_id,
)


def check_tune(cfg: DictConfig) -> list[Param]:
    """Reject bad study settings with one line naming the field, before any work starts."""
    t = cfg.tune
    integer(t.n_trials, "tune.n_trials", 1)
    if t.timeout is not None:
        number(t.timeout, "tune.timeout", low=0.0, low_open=True,
               form="a number of seconds > 0, or null")
    integer(t.seed, "tune.seed", 0)
    require(isinstance(t.study_name, str) and t.study_name != "", "tune.study_name",
            "a non-empty string", t.study_name)
    require(not ("'" in t.study_name and '"' in t.study_name), "tune.study_name",
            "a name without both quote kinds (' and \"), which no MLflow filter can hold",
            t.study_name)
    require(isinstance(t.handoff, str) and t.handoff.endswith(".yaml"), "tune.handoff",
            "a path ending in .yaml", t.handoff)
    for key in ("heartbeat_interval", "grace_period", "n_startup_trials"):
        integer(t[key], f"tune.{key}", 1)
    if cfg.model.name in SLIP:  # the side-slip observers: their own data and nets
        from lbo.learn.slip_run import check as check_slip

        check_slip(cfg)
    else:
        check(cfg)
    return search_space(cfg)


# --- Optuna ---------------------------------------------------------------------------------


def _describe(trial: FrozenTrial, space: list[Param]) -> str:
    params = " ".join(f"{p.key}={short_value(p.decode(trial.params[p.key]))}" for p in space
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


# --- trials ---------------------------------------------------------------------------------


def _slug(name: str) -> str:
    """A study name as one folder name: anything but letters, digits and ``._+-`` becomes _."""
    return re.sub(r"[^A-Za-z0-9._+-]", "_", name).lstrip(".") or "study"


def trial_config(cfg: DictConfig, values: dict[str, Any], number: int, study_name: str,
                 output_dir: Path) -> DictConfig:
    """The training config of one trial: ``cfg`` with the sampled values, its own output folder,
    and nothing that reads the test set."""
    from lightning.pytorch.callbacks import ProgressBar

    from lbo.learn.builders import targets
    from lbo.learn.callbacks import Evaluation

    out = copy.deepcopy(cfg)
    with open_dict(out):
        for key, value in values.items():
            OmegaConf.update(out, key, value, merge=False)
        # the study's name in the path: two studies run from one folder (or two workers of
        # two studies) number their trials from 0 alike, and a trial never trains into another
        # study's trial folder (a finished run's, which training refuses)
        out.output_dir = str(output_dir / _slug(study_name) / f"trial_{number:03d}")
        del out.tune
        callbacks = out.get("callbacks") or {}
        for name in list(callbacks):
            # Tuning must never see the test set: the evaluation callback scores the test grid
            # at the end of fit, so it is left out of every trial. Progress bars would bury the
            # one line per trial.
            if targets(callbacks[name], Evaluation) or targets(callbacks[name], ProgressBar):
                del callbacks[name]
        out.trainer.enable_progress_bar = False
        out.trainer.enable_model_summary = False
        out.keep_onnx = False  # a trial is never observed: no graphs to keep for lbo.observe
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
    The best trial is the best completed one whose settings lie in the current search space.

    Raises
    ------
    LboError
        For bad settings (before any trial), a resumed study whose stored distributions the
        search space no longer matches, or when the study has no completed trial.
    KeyboardInterrupt
        On Ctrl-C, after the running trial was failed, its run and the study's run closed.
    """
    space = check_tune(cfg)
    pruner = make_pruner(cfg.tune.pruner)
    storage = open_storage(cfg.tune.storage, cfg.tune.heartbeat_interval,
                           cfg.tune.grace_period)
    try:
        return _run_study(cfg, space, pruner, storage)
    finally:
        close_storage(storage)  # a worker leaves no connection open, whatever happened


def check_same_logs(study: optuna.Study, cfg: DictConfig) -> None:
    """On ``data=logs``, a study holds the trials of one set of logs (the digest of their
    bytes): resuming it on other logs would compare losses of different data. Raises one line
    naming ``tune.study_name``; records the digest on a new study."""
    from lbo.learn.builders import logs_spec
    from lbo.logs.sets import is_logs

    if not is_logs(cfg):
        return
    digest = logs_spec(cfg).digest
    held = study.user_attrs.get("logs_digest")
    if held is not None and held != digest:
        raise LboError(f"tune.study_name: study {study.study_name!r} was tuned on other logs "
                       f"(logs-{held}, these are logs-{digest}); give another tune.study_name")
    study.set_user_attr("logs_digest", digest)


def _run_study(cfg: DictConfig, space: list[Param], pruner: optuna.pruners.BasePruner,
               storage: optuna.storages.RDBStorage) -> dict[str, Any]:
    t = cfg.tune
    shown = redact(t.storage)
    sampler = TrialSeededTPESampler(seed=t.seed, n_startup_trials=t.n_startup_trials)
    study = optuna.create_study(study_name=t.study_name, storage=storage, sampler=sampler,
                                pruner=pruner, direction="minimize", load_if_exists=True)
    check_resumed(study.get_trials(deepcopy=False), space, f"{t.study_name!r} in {shown}")
    check_same_logs(study, cfg)
    for key, value in (("model", cfg.model.name), ("window", cfg.model.window),
                       ("data", cfg.data.name)):
        study.set_user_attr(key, value)
    output = Path(cfg.output_dir)
    from lightning.pytorch.loggers import MLFlowLogger

    from lbo.learn.builders import targets

    tracking = targets(cfg.get("logger"), MLFlowLogger)
    claim = ClaimLock(storage, t.storage, t.study_name)
    new: list[int] = []
    stopped: list[int] = []  # trials interrupted here (Ctrl-C), failed by Optuna
    diverged: list[int] = []  # trials whose training diverged since the last one completed
    verbosity = optuna.logging.get_verbosity()

    def objective(trial: optuna.Trial) -> float:
        claim.release()  # the trial is RUNNING in the storage: other workers count it now
        for key, value in worker_id().items():
            trial.set_user_attr(key, value)
        values = {p.key: p.suggest(trial) for p in space}
        trial_cfg = trial_config(cfg, values, trial.number, t.study_name, output)
        trial.set_user_attr("output_dir", trial_cfg.output_dir)
        tags = {"optuna_study": t.study_name, "optuna_trial": str(trial.number)}
        if run is not None:
            tags["mlflow.parentRunId"] = run.run_id
        try:
            interrupts.check()
            from lbo.tuning.callbacks import Pruning

            return train(trial_cfg, callbacks=[Pruning(trial), interrupts],
                         tags=tags)["val_loss"]
        except optuna.TrialPruned:
            raise
        except TrainingDiverged:
            diverged.append(trial.number)
            if run is not None:
                run.close_trial(trial.user_attrs.get(RUN_ATTR), TrialState.FAIL)
            raise
        except BaseException as e:
            # Optuna re-raises the error without calling the study callbacks: close the run here
            stop = isinstance(e, (KeyboardInterrupt, SystemExit))
            if stop:
                stopped.append(trial.number)
                # Optuna would log the interrupt's traceback as the trial's failure: tune says
                # what happened in one line instead (verbosity restored as tune ends)
                optuna.logging.set_verbosity(max(verbosity, optuna.logging.ERROR))
            if run is not None:
                run.close_trial(trial.user_attrs.get(RUN_ATTR), TrialState.FAIL,
                                interrupted=stop)
            if isinstance(e, SystemExit):
                # Lightning turns Ctrl-C (and SIGTERM) during fit into sys.exit(1), which
                # Optuna does not catch: its trial would stay RUNNING. As KeyboardInterrupt,
                # Optuna fails the trial and raises it on.
                raise KeyboardInterrupt from e
            raise

    def progress(study: optuna.Study, trial: FrozenTrial) -> None:
        new.append(trial.number)
        if trial.state != TrialState.FAIL:
            diverged.clear()
        if run is not None:
            run.mark(trial)
        print(_describe(trial, space), flush=True)
        left = remaining - len(new)
        if len(new) == 1 and left > 0 and trial.duration is not None:
            from lbo.learn.eta import more

            took = trial.duration.total_seconds()  # the first trial, as the rest will run
            print(more(left, "trial", took, "the first's time") + "; pruning can only shorten it",
                  flush=True)

    run = StudyRun(cfg, study, shown) if tracking else None
    status, handoff, best = "FAILED", None, None
    remaining = t.n_trials  # the trials this run adds, counted once the study is read
    from lbo.tuning.callbacks import Interrupts

    lightning_log = logging.getLogger("lightning.pytorch")
    lightning_level = lightning_log.level  # put back as tune ends, as Optuna's verbosity is
    if _QUIET["lightning"]:  # Lightning sets its logger to INFO when first imported, above
        lightning_log.setLevel(logging.WARNING)
    interrupts = Interrupts()
    interrupts.install()
    try:
        # from here on the study's run is open: every way out below closes it
        finished = len(study.get_trials(deepcopy=False, states=FINISHED))
        remaining = t.n_trials - finished
        print(f"study {t.study_name} in {shown}: {finished} of {t.n_trials} trials finished"
              + (f", running {remaining} more" if remaining > 0 else ""), flush=True)
        # one trial at a time, each claimed under the study's lock: workers sharing the
        # study stop once it holds n_trials finished (or running) trials, and never overshoot
        start = time.monotonic()
        while t.timeout is None or time.monotonic() - start < t.timeout:
            interrupts.check()
            if len(diverged) >= t.n_trials:  # a space where every trial diverges never ends
                raise LboError(f"study {t.study_name}: {len(diverged)} trials diverged in a row "
                               f"(trials {', '.join(map(str, diverged))}); lower the "
                               "learning rates of tune.search_space")
            claim.acquire()
            try:
                if not needs_trial(study, t.n_trials):
                    break
                # a diverged trial is FAIL (not counted); the study goes on with the next
                study.optimize(objective, n_trials=1, callbacks=[progress],
                               catch=(TrainingDiverged,))
            finally:
                claim.release()
        best, better = best_trials(study, space)
        if best is not None and better is not None:
            print(outside_note(better, best, space), flush=True)
        if best is not None:
            handoff = write_handoff(cfg, study, space, shown, best)
        status = "FINISHED"
    except KeyboardInterrupt:
        status = "KILLED"
        raise
    finally:
        try:
            with _no_interrupts():  # a second Ctrl-C must not leave the runs open
                optuna.logging.set_verbosity(verbosity)
                lightning_log.setLevel(lightning_level)
                failed: list[int] = []
                try:
                    if status != "FINISHED":
                        failed = fail_own_trials(study)
                except Exception:  # best effort: the error on its way out says more
                    pass
                finally:
                    if run is not None:
                        run.finish(study, space, best, handoff, status)
                if status == "KILLED":
                    done = len(study.get_trials(deepcopy=False, states=FINISHED))
                    lost = sorted({*failed, *stopped})
                    which = (f", trial{'s' if len(lost) > 1 else ''} "
                             f"{', '.join(map(str, lost))} failed") if lost else ""
                    print(f"interrupted: study {t.study_name} in {shown}: {done} of {t.n_trials} "
                          f"trials finished{which}; rerun the same command to finish it",
                          file=sys.stderr, flush=True)
        finally:
            interrupts.uninstall()

    counts = {s: len(study.get_trials(deepcopy=False, states=(s,))) for s in TrialState}
    if best is None:
        if counts[TrialState.COMPLETE]:
            # none inside, some completed: the best of them lies outside
            better = cast(FrozenTrial, best_trials(study, space)[1])
            raise LboError(f"study {t.study_name}: none of its {counts[TrialState.COMPLETE]} "
                           f"completed trials lies in the current search space (trial "
                           f"{better.number}: {outside_space(better, space)}), so no hand-off "
                           f"was written; rerun with a larger tune.n_trials")
        raise LboError(f"study {t.study_name}: no trial has completed "
                       f"({counts[TrialState.PRUNED]} pruned, {counts[TrialState.FAIL]} failed),"
                       f" so no hand-off was written; rerun with a larger tune.n_trials")
    # a best trial: its hand-off was written
    command = train_command(cfg.model.name, cast(Path, handoff), hydra_searchpath(),
                            cfg.model.features)
    params = {p.key: p.decode(best.params[p.key]) for p in space if p.key in best.params}
    print(f"best: trial {best.number}, val_loss {best.value:.6g}: "
          + " ".join(f"{k}={short_value(v)}" for k, v in params.items()))
    print(f"train with: {command}")
    print(f"tuned: {handoff}", flush=True)
    return {"study_name": t.study_name, "storage": shown, "best_value": best.value,
            "best_params": params, "best_trial": best.number, "new_trials": new,
            "n_complete": counts[TrialState.COMPLETE], "n_pruned": counts[TrialState.PRUNED],
            "n_failed": counts[TrialState.FAIL], "handoff": handoff, "train_command": command,
            "parent_run_id": run.run_id if run is not None else None}


@contextlib.contextmanager
def _no_interrupts() -> Iterator[None]:
    """Ignore Ctrl-C (in the main thread) while the study's runs are being closed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


_QUIET = {"lightning": False}


def quiet() -> None:
    """One line per trial from :func:`tune` instead of Optuna's and Lightning's own chatter."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    _QUIET["lightning"] = True
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)


def _quiet_tune(cfg: DictConfig) -> float:
    quiet()
    try:
        return tune(cfg)["best_value"]
    except KeyboardInterrupt:  # tune said what it closed and how to go on: no traceback
        raise SystemExit(130) from None


main = entry("tune", _quiet_tune, short_model_keys=True)


if __name__ == "__main__":
    sys.exit(main())
