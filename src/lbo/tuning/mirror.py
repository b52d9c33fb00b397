"""The MLflow side of an ``lbo.tune`` study: one parent run per study, a child run per trial,
the best settings and the study's figures."""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path
from typing import Any

import optuna
from omegaconf import DictConfig, OmegaConf
from optuna.trial import FrozenTrial, TrialState

from lbo.core.redact import scrub
from lbo.tracking.runs import logger_experiment
from lbo.tuning.search import Param

#: MLflow run status for each final Optuna state; the child run also gets tag ``optuna_state``.
MLFLOW_STATUS = {TrialState.COMPLETE: "FINISHED", TrialState.PRUNED: "KILLED",
                 TrialState.FAIL: "FAILED"}
PARENT_ATTR = "mlflow_parent_run_id"   # study user attribute: the study's MLflow run
RUN_ATTR = "mlflow_run_id"             # trial user attribute: the trial's MLflow run


def literal(value: str) -> str:
    """``value`` as a string literal of an MLflow filter: in single quotes, or in double quotes
    when it holds a single quote (MLflow's filters have no escapes; :func:`lbo.tune.check_tune`
    refuses a study name with both)."""
    value = str(value)
    if "'" not in value:
        return f"'{value}'"
    if '"' not in value:
        return f'"{value}"'
    raise ValueError(f"{value!r} holds both quote kinds: no MLflow filter can name it")


class StudyRun:
    """The study's parent MLflow run, found again through the study on a rerun, so that a
    resumed or shared study keeps one parent. Child runs are the trials' training runs."""

    def __init__(self, cfg: DictConfig, study: optuna.Study, storage: str) -> None:
        self.client, exp_id = logger_experiment(cfg.logger)
        self.exp_id = exp_id
        self.run_id = study.user_attrs.get(PARENT_ATTR)
        if self._status(self.run_id) is not None:
            self.client.update_run(self.run_id, status="RUNNING")
            return
        name = study.study_name
        storage = scrub(storage)
        own = self.client.create_run(exp_id, run_name=f"study-{name}", tags={
            "optuna_study": name, "optuna_storage": storage, "optuna_role": "study",
            "model": cfg.model.name, "window": str(cfg.model.window), "data": cfg.data.name}).info
        try:
            self.run_id = self._first(exp_id, name, storage, own)
            if self.run_id != own.run_id:  # a worker that started with this one was first
                self.client.delete_run(own.run_id)
                return
            study.set_user_attr(PARENT_ATTR, self.run_id)
            for key, value in {"study_name": name, "storage": storage,
                               "model": cfg.model.name, "window": cfg.model.window,
                               "data": cfg.data.name, "sampler": "TPE",
                               "sampler_seed": cfg.tune.seed,
                               "pruner": cfg.tune.pruner.get("_target_", "")}.items():
                self.client.log_param(self.run_id, key, value)
            self.client.log_text(self.run_id, OmegaConf.to_yaml(cfg.tune.search_space),
                                 "search_space.yaml")
        except BaseException as e:  # the run opened: it must not stay RUNNING
            self.client.set_terminated(own.run_id, _ended_by(e))
            raise

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
                    pruned_epoch: int | None = None, interrupted: bool = False) -> None:
        """End a trial's run with its Optuna state; an interrupted trial (Ctrl-C) is FAIL in
        Optuna and FAILED here, tagged ``optuna_interrupted``."""
        if run_id is None or state not in MLFLOW_STATUS:
            return
        self.client.set_tag(run_id, "optuna_state", state.name)
        if pruned_epoch is not None:
            self.client.set_tag(run_id, "optuna_pruned_epoch", str(pruned_epoch))
        if interrupted:
            self.client.set_tag(run_id, "optuna_interrupted", "true")
        self.client.set_terminated(run_id, MLFLOW_STATUS[state])

    def close_stale(self, study: optuna.Study) -> None:
        """Trials failed for a silent heartbeat left their runs RUNNING: close them FAILED.

        A worker killed after its trial's run opened but before the trial recorded the run
        (``RUN_ATTR``, at fit start) leaves a run only its tags name: found by those."""
        failed = study.get_trials(deepcopy=False, states=(TrialState.FAIL,))
        for trial in failed:
            if self._status(trial.user_attrs.get(RUN_ATTR)) == "RUNNING":
                self.mark(trial)
        numbers = {str(t.number) for t in failed}
        if not numbers:
            return
        live = self.client.search_runs(
            [self.exp_id], f"tags.optuna_study = {literal(study.study_name)} and "
            "attributes.status = 'RUNNING'", max_results=1000)
        for r in live:
            if (r.data.tags.get("optuna_trial") in numbers
                    and r.data.tags.get("mlflow.parentRunId") == self.run_id):
                self.close_trial(r.info.run_id, TrialState.FAIL)

    def finish(self, study: optuna.Study, space: list[Param], best: FrozenTrial | None,
               handoff: Path | None, status: str) -> None:
        """Close the runs of stale trials, log the study's outcome, and end the parent run with
        ``status``; it ends FAILED (KILLED on Ctrl-C) when logging the outcome fails."""
        try:
            self.close_stale(study)
            self.summarise(study, space, best, handoff)
        except BaseException as e:
            self.client.set_terminated(self.run_id, "KILLED" if status == "KILLED"
                                       else _ended_by(e))
            raise
        self.client.set_terminated(self.run_id, status)

    def summarise(self, study: optuna.Study, space: list[Param], best: FrozenTrial | None,
                  handoff: Path | None) -> None:
        """The trial counts, the best trial (``best``: the best that fits the search space)
        and its settings, the study's figures and the hand-off, logged to the parent run."""
        counts = {s: len(study.get_trials(deepcopy=False, states=(s,))) for s in TrialState}
        finished = counts[TrialState.COMPLETE] + counts[TrialState.PRUNED]
        for state in (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL):
            self.client.log_metric(self.run_id, f"n_{state.name.lower()}", counts[state],
                                   step=finished)
        if best is not None:
            self.client.log_metric(self.run_id, "best_val_loss", best.value, step=finished)
            self.client.set_tag(self.run_id, "best_trial", str(best.number))
            # tags, not params: a resumed study may find a better trial, and MLflow params
            # cannot change once logged
            for p in space:
                if p.key in best.params:
                    self.client.set_tag(self.run_id, f"best.{p.key}",
                                        str(p.decode(best.params[p.key])))
        if counts[TrialState.COMPLETE]:
            with tempfile.TemporaryDirectory() as tmp:
                for png in _figures(study, Path(tmp)):
                    self.client.log_artifact(self.run_id, str(png))
        if handoff is not None:
            self.client.log_artifact(self.run_id, str(handoff), artifact_path="tuned")


def _ended_by(error: BaseException) -> str:
    """The MLflow status of a run ended by ``error``: KILLED for Ctrl-C, else FAILED."""
    return "KILLED" if isinstance(error, KeyboardInterrupt) else "FAILED"


def _figures(study: optuna.Study, folder: Path) -> list[Path]:
    """The optimisation history and the trials' validation curves, as PNGs."""
    import matplotlib.pyplot as plt
    from optuna.visualization import matplotlib as ovm

    from lbo.core import plots

    out = []
    # optuna's plots switch the global style to ggplot: keep that to these two figures
    with warnings.catch_warnings(), plt.rc_context():
        warnings.simplefilter("ignore")  # optuna marks its matplotlib plots experimental
        # each names its objective: a trial's best validation loss, and the loss each epoch
        ax = ovm.plot_optimization_history(study, target_name="val_loss (best of the trial)")
        ax.set_ylabel("val_loss: validation loss (lower is better)")
        out.append(plots.save(ax.figure, folder / "optimization_history.png"))
        ax = ovm.plot_intermediate_values(study)
        ax.set(xlabel="epoch", ylabel="val_loss after the epoch (lower is better)")
        out.append(plots.save(ax.figure, folder / "intermediate_values.png"))
    return out


