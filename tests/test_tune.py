import os
import re
import signal
import socket
import subprocess
import sys
import time
import warnings

import mlflow
import optuna
import pytest
from hydra.errors import MissingConfigException
from omegaconf import open_dict

from helpers import cli, compose_cfg
from lbo.core.errors import LboError
from lbo.core.paths import CONF_DIR
from lbo.train import check
from lbo.tune import open_storage, search_space, trial_config, tune
from lbo.tuning.mirror import StudyRun, literal
from lbo.tuning.search import TrialSeededTPESampler

optuna.logging.set_verbosity(optuna.logging.WARNING)


@pytest.fixture(scope="module")
def tracking(tmp_path_factory) -> str:
    """One MLflow store for the module: creating its tables costs seconds."""
    return f"sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"


def tune_cfg(tmp_path, smoke_data, tracking, *overrides, search="cnn"):
    """A smoke study whose storage, runs, outputs and hand-off all live under tmp_path."""
    handoff = tmp_path / "conf" / "tuned" / f"{search or 'cnn'}.yaml"
    return compose_cfg("tune", [
        *([f"hparams_search={search}"] if search else []), "experiment=smoke",
        f"data.root={smoke_data.parent}", "trainer.limit_train_batches=5",
        f"output_dir={tmp_path / 'out'}", f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
        f"tune.handoff={handoff}", f"logger.tracking_uri={tracking}", *overrides])


def study_runs(tracking, study_name):
    client = mlflow.MlflowClient(tracking)
    exp = client.get_experiment_by_name("lbo-smoke")
    if exp is None:  # nothing logged yet
        return client, [], []
    found = client.search_runs([exp.experiment_id], f"tags.optuna_study = {literal(study_name)}")
    parents = [r for r in found if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in found if "mlflow.parentRunId" in r.data.tags]
    return client, parents, children


# --- a study, resumed, handed off -------------------------------------------------------------


def test_rerun_adds_only_missing_trials_and_hands_off(tmp_path, smoke_data, tracking, capsys):
    first = tune(tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=2",
                          "tune.study_name=resume"))
    assert first["new_trials"] == [0, 1]
    second = tune(tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=3",
                           "tune.study_name=resume"))
    assert second["new_trials"] == [2]  # only the missing trial ran
    again = tune(tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=3",
                          "tune.study_name=resume"))
    assert again["new_trials"] == []
    study = optuna.load_study(study_name="resume", storage=f"sqlite:///{tmp_path / 'optuna.db'}")
    assert [t.number for t in study.trials] == [0, 1, 2]
    assert all(len(t.intermediate_values) == 2 for t in study.trials)  # val_loss every epoch

    printed = capsys.readouterr().out.strip().splitlines()
    # after its first trial, the first run said how long the other one would take
    said = [line for line in printed if line.startswith("estimate: ")]
    assert len(said) == 1 and re.match(r"estimate: 1 more trial x \d+\.\d s \(the first's "
                                       r"time\): (about \d+ s|under)", said[0]), said
    handoff = tmp_path / "conf" / "tuned" / "cnn.yaml"
    assert printed[-1] == f"tuned: {handoff}"
    assert "+tuned=cnn" in printed[-2] and "window=20,40,60,80" in printed[-2]

    # the hand-off composes into training for every window, and training accepts it
    best = again["best_params"]
    assert set(best) == {"optimizer.lr", "optimizer.weight_decay", "batch_size",
                         "model.conv_channels", "model.feature_channels", "model.dense_units"}
    cfg = compose_cfg("train", ["model=cnn", "+tuned=cnn", "window=60",
                                f"hydra.searchpath=[file://{tmp_path / 'conf'}]"])
    assert cfg.model.window == 60
    assert cfg.optimizer.lr == best["optimizer.lr"] and cfg.batch_size == best["batch_size"]
    assert cfg.model.conv_channels == best["model.conv_channels"]
    check(cfg)

    # one parent run for the study, however often it ran; a child run per trial
    client, parents, children = study_runs(tracking, "resume")
    assert len(parents) == 1 and parents[0].info.run_id == again["parent_run_id"]
    parent = client.get_run(parents[0].info.run_id)
    assert parent.info.status == "FINISHED"
    assert parent.data.tags["best.optimizer.lr"] == str(best["optimizer.lr"])
    assert parent.data.metrics["best_val_loss"] == pytest.approx(again["best_value"])
    logged = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"optimization_history.png", "intermediate_values.png", "tuned"} <= logged
    assert sorted(r.data.tags["optuna_trial"] for r in children) == ["0", "1", "2"]
    for r in children:
        assert r.data.tags["mlflow.parentRunId"] == parent.info.run_id
        assert r.info.status == "FINISHED" and r.data.tags["optuna_state"] == "COMPLETE"
        assert len(client.get_metric_history(r.info.run_id, "val_loss")) == 2
        # the test grid is never scored while tuning
        assert not any(k.startswith("test_") for k in r.data.metrics)
    assert not list((tmp_path / "out").rglob("evaluation.csv"))


def test_a_pruned_trial_is_pruned_in_optuna_and_mlflow(tmp_path, smoke_data, tracking):
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=1", "tune.study_name=pruned")
    with open_dict(cfg):  # prunes every trial at its first report
        cfg.tune.pruner = {"_target_": "optuna.pruners.ThresholdPruner", "upper": 0.0}
    with pytest.raises(LboError, match=r"no trial has completed \(1 pruned, 0 failed\)"):
        tune(cfg)
    study = optuna.load_study(study_name="pruned", storage=cfg.tune.storage)
    assert [t.state for t in study.trials] == [optuna.trial.TrialState.PRUNED]
    assert list(study.trials[0].intermediate_values) == [0]
    client, parents, children = study_runs(tracking, "pruned")
    [child] = children
    assert child.info.status == "KILLED"
    assert child.data.tags["optuna_state"] == "PRUNED"
    assert child.data.tags["optuna_pruned_epoch"] == "0"
    assert len(client.get_metric_history(child.info.run_id, "val_loss")) == 1
    assert parents[0].info.status == "FINISHED"
    assert not (tmp_path / "conf" / "tuned" / "cnn.yaml").exists()


@pytest.mark.parametrize("recorded", [True, False])
def test_a_killed_trial_is_failed_then_retried(tmp_path, smoke_data, tracking, recorded):
    """``recorded=False``: killed after its run opened but before the trial recorded it."""
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=1", "tune.study_name=killed",
                   "tune.heartbeat_interval=1", "tune.grace_period=1")
    # a process that died in trial 0, after drawing its learning rate and opening its run
    storage = open_storage(cfg.tune.storage, 1, 1)
    study = optuna.create_study(study_name="killed", storage=storage)
    parent = StudyRun(cfg, study, "the study's storage").run_id
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # optuna would rather ask inside Study.optimize
        dead = study.ask()
    lr = dead.suggest_float("optimizer.lr", 1e-4, 3e-3, log=True)  # the search space's range
    storage.record_heartbeat(dead._trial_id)
    client = mlflow.MlflowClient(tracking)
    name = cfg.logger.experiment_name  # the study's own: lbo-<data>
    exp = client.get_experiment_by_name(name) or client.get_experiment(client.create_experiment(
        name, artifact_location=cfg.logger.artifact_location))
    run_id = client.create_run(exp.experiment_id, tags={
        "optuna_study": "killed", "optuna_trial": "0", "mlflow.parentRunId": parent}).info.run_id
    if recorded:
        dead.set_user_attr("mlflow_run_id", run_id)
    time.sleep(2.1)  # its heartbeat goes stale (SQLite keeps whole seconds)

    out = tune(cfg)
    assert out["new_trials"] == [1]
    zero, one = optuna.load_study(study_name="killed", storage=cfg.tune.storage).trials
    assert zero.state == optuna.trial.TrialState.FAIL
    assert one.state == optuna.trial.TrialState.COMPLETE
    assert one.params["optimizer.lr"] == lr and one.system_attrs["failed_trial"] == 0
    dead_run = client.get_run(run_id)
    assert dead_run.info.status == "FAILED" and dead_run.data.tags["optuna_state"] == "FAIL"


def test_a_running_trial_of_a_gone_worker_on_this_machine_does_not_count(
        tmp_path, smoke_data, tracking):
    """A worker killed (or interrupted) on this machine left its trial RUNNING, its heartbeat
    not yet stale: a rerun fails the trial at once (and retries its settings), so the study
    still ends with n_trials finished."""
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=1", "tune.study_name=gone")
    storage = open_storage(cfg.tune.storage, 60, 180)
    study = optuna.create_study(study_name="gone", storage=storage)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dead = study.ask()
    lr = dead.suggest_float("optimizer.lr", 1e-4, 3e-3, log=True)
    storage.record_heartbeat(dead._trial_id)  # fresh: the heartbeat alone would wait 180 s
    gone = subprocess.Popen(["true"])
    gone.wait()
    dead.set_user_attr("worker", f"{socket.gethostname()}:{gone.pid}")

    out = tune(cfg)
    assert out["new_trials"] == [1]
    zero, one = optuna.load_study(study_name="gone", storage=cfg.tune.storage).trials
    assert zero.state == optuna.trial.TrialState.FAIL
    assert one.state == optuna.trial.TrialState.COMPLETE
    assert one.params["optimizer.lr"] == lr and one.system_attrs["failed_trial"] == 0


@pytest.mark.slow
def test_ctrl_c_fails_the_trial_kills_the_study_run_and_a_rerun_finishes_n_trials(
        tmp_path, smoke_data, tracking):
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    args = [sys.executable, "-m", "lbo.tune", "hparams_search=cnn", "experiment=smoke",
            f"data.root={smoke_data.parent}", "trainer.limit_train_batches=5",
            "tune.n_trials=3", f"tune.storage={storage}", "tune.study_name=ctrl-c",
            f"tune.handoff={tmp_path / 'tuned' / 'cnn.yaml'}", f"output_dir={tmp_path / 'out'}",
            f"logger.tracking_uri={tracking}"]
    # the first trial trains until it is interrupted: a short one could finish between the
    # poll that sees it fitting and the signal (seen on a busy machine: the trial COMPLETE)
    endless = ["trainer.max_epochs=100000", "callbacks.early_stopping.patience=100000"]
    proc = subprocess.Popen([*args, *endless, f"hydra.run.dir={tmp_path / 'a'}"], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    # Ctrl-C (the terminal signals the whole process group) while a trial trains
    reader, deadline, hit = None, time.monotonic() + 240, None
    try:
        while hit is None and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
            try:
                reader = reader or optuna.storages.RDBStorage(
                    storage, engine_kwargs={"connect_args": {"timeout": 60}})
                study = optuna.load_study(study_name="ctrl-c", storage=reader)
            except (KeyError, RuntimeError, sqlalchemy_errors()):  # not created yet
                continue
            for t in study.get_trials(states=(optuna.trial.TrialState.RUNNING,)):
                if "mlflow_run_id" in t.user_attrs:  # its run is open: Lightning is fitting
                    os.killpg(proc.pid, signal.SIGINT)
                    hit = t.number
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert hit is not None, "the study finished before a trial could be interrupted"
    # the study and MLflow agree: the trial failed, its run FAILED, the study's run KILLED
    study = optuna.load_study(study_name="ctrl-c", storage=storage)
    assert study.trials[hit].state == optuna.trial.TrialState.FAIL, err[-3000:]
    assert not study.get_trials(states=(optuna.trial.TrialState.RUNNING,))
    client, parents, children = study_runs(tracking, "ctrl-c")
    assert [p.info.status for p in parents] == ["KILLED"]
    [child] = [c for c in children if c.data.tags["optuna_trial"] == str(hit)]
    assert child.info.status == "FAILED" and child.data.tags["optuna_state"] == "FAIL"
    assert child.data.tags["optuna_interrupted"] == "true"
    # one line on how to go on, no traceback, the shell's exit status for Ctrl-C
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err
    assert re.fullmatch(
        rf"interrupted: study ctrl-c in {re.escape(storage)}: {hit} of 3 trials finished, "
        rf"trial {hit} failed; rerun the same command to finish it", err.strip().splitlines()[-1])

    # the rerun in this process: only the Ctrl-C needs a process of its own
    again = cli("lbo.tune", *args[3:], f"hydra.run.dir={tmp_path / 'b'}")
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.startswith(f"study ctrl-c in {storage}: {hit} of 3 trials finished, "
                                   f"running {3 - hit} more")
    study = optuna.load_study(study_name="ctrl-c", storage=storage)
    states = [t.state for t in study.trials]
    assert states.count(optuna.trial.TrialState.COMPLETE) \
        + states.count(optuna.trial.TrialState.PRUNED) == 3
    assert optuna.trial.TrialState.RUNNING not in states
    client, parents, children = study_runs(tracking, "ctrl-c")
    assert [p.info.status for p in parents] == ["FINISHED"]
    assert "RUNNING" not in [c.info.status for c in children]
    assert len(children) == len(study.trials)


def sqlalchemy_errors():
    from sqlalchemy.exc import OperationalError

    return OperationalError


def test_a_study_name_with_a_quote_closes_its_runs(tmp_path, smoke_data, tracking):
    """MLflow filters name the study: a quote in its name must not break them (here: closing
    the run a killed worker left RUNNING), nor leave the study's run RUNNING."""
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=1",
                   'tune.study_name="it\'s"')
    assert cfg.tune.study_name == "it's"
    storage = open_storage(cfg.tune.storage, 60, 180)
    study = optuna.create_study(study_name="it's", storage=storage)
    parent = StudyRun(cfg, study, "the study's storage").run_id
    study.add_trial(optuna.trial.create_trial(state=optuna.trial.TrialState.FAIL))
    client = mlflow.MlflowClient(tracking)
    exp = client.get_experiment_by_name("lbo-smoke")
    left = client.create_run(exp.experiment_id, tags={
        "optuna_study": "it's", "optuna_trial": "0", "mlflow.parentRunId": parent}).info.run_id

    out = tune(cfg)
    assert out["new_trials"] == [1] and out["parent_run_id"] == parent
    assert client.get_run(left).info.status == "FAILED"
    assert client.get_run(parent).info.status == "FINISHED"
    assert literal("it's") == '"it\'s"' and literal('say "x"') == """'say "x"'"""
    # the trial's run holds its weights, as a logged model named without the quote
    trial = client.search_runs([exp.experiment_id], "tags.optuna_trial = '1'")[0].info
    assert [f.path for f in client.list_artifacts(trial.run_id, "checkpoints")] == [
        "checkpoints/best.ckpt"]
    models = client.search_logged_models([exp.experiment_id])
    assert [m.name for m in models if m.source_run_id == trial.run_id] == ["it_s-trial1"]


def test_a_diverged_trial_fails_and_the_study_goes_on_until_too_many_diverge(
        tmp_path, smoke_data, tracking, capsys):
    """A learning rate that diverges fails its trial (FAIL, run FAILED) and the study goes on
    with the next; a space where every trial diverges stops after n_trials in a row."""
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=2", "tune.study_name=div",
                   "trainer.max_epochs=1", "trainer.limit_train_batches=3",
                   "tune.search_space.optimizer.lr.low=1e299",
                   "tune.search_space.optimizer.lr.high=1e300")
    with pytest.raises(LboError, match=r"^study div: 2 trials diverged in a row \(trials 0, 1\); "
                                       "lower the learning rates of tune.search_space$"):
        tune(cfg)
    study = optuna.load_study(study_name="div", storage=cfg.tune.storage)
    assert [t.state.name for t in study.trials] == ["FAIL", "FAIL"]
    _, parents, children = study_runs(tracking, "div")
    assert [r.info.status for r in parents] == ["FAILED"]
    assert sorted(r.info.status for r in children) == ["FAILED", "FAILED"]
    assert not (tmp_path / "conf" / "tuned" / "cnn.yaml").exists()


def test_an_error_after_the_study_run_opened_ends_it_failed(tmp_path, smoke_data, tracking,
                                                           monkeypatch):
    from lbo.tuning import mirror as study_mlflow

    def broken(*args, **kwargs):
        raise RuntimeError("no figures today")

    monkeypatch.setattr(study_mlflow, "_figures", broken)
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=1",
                   "tune.study_name=broken")
    with pytest.raises(RuntimeError, match="no figures today"):
        tune(cfg)
    _, parents, children = study_runs(tracking, "broken")
    assert [p.info.status for p in parents] == ["FAILED"]
    assert [c.info.status for c in children] == ["FINISHED"]


# --- a resumed study whose search space changed -----------------------------------------------


def old_trial(value, lr, batch_size, lr_high=1e-2, choices=(64, 128, 256, 512)):
    """A completed trial of an earlier search space (lr up to ``lr_high``, batch sizes
    ``choices``)."""
    dists = {"optimizer.lr": optuna.distributions.FloatDistribution(1e-4, lr_high, log=True),
             "batch_size": optuna.distributions.CategoricalDistribution(choices)}
    return optuna.trial.create_trial(params={"optimizer.lr": lr, "batch_size": batch_size},
                                     distributions=dists, value=value)


def test_a_changed_categorical_space_is_refused_before_any_trial(tmp_path, smoke_data,
                                                                 tracking):
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=2", "tune.study_name=moved",
                   "tune.search_space.batch_size.choices=[64,128]")
    study = optuna.create_study(study_name="moved", storage=cfg.tune.storage)
    study.add_trial(old_trial(0.9, 1e-3, 256))
    with pytest.raises(LboError) as err:
        tune(cfg)
    assert str(err.value) == (
        f"tune.search_space.batch_size: study 'moved' in {cfg.tune.storage} was run with "
        "choices [64, 128, 256, 512], the search space now has [64, 128]; restore its "
        "choices, or start a new study with another tune.study_name")
    assert len(optuna.load_study(study_name="moved", storage=cfg.tune.storage).trials) == 1
    _, parents, _ = study_runs(tracking, "moved")
    assert parents == []  # refused before the study's run opened


@pytest.mark.parametrize("stored, message", [
    (optuna.distributions.FloatDistribution(32, 256),
     "was run with a float distribution, the search space now has an int one; restore its "
     "type"),
    (optuna.distributions.IntDistribution(32, 256),
     "was run with log: false, the search space now has log: true; restore its log scale"),
    (optuna.distributions.IntDistribution(16, 512, log=True), None),  # a range may change
])
def test_a_changed_distribution_kind_or_scale_is_refused(tmp_path, smoke_data, tracking,
                                                          stored, message):
    from lbo.tuning.search import check_resumed

    space = search_space(tune_cfg(tmp_path, smoke_data, tracking))
    trial = optuna.trial.create_trial(params={"model.dense_units": 64},
                                      distributions={"model.dense_units": stored}, value=1.0)
    if message is None:
        check_resumed([trial], space, "'s' in sqlite:///x.db")
        return
    with pytest.raises(LboError) as err:
        check_resumed([trial], space, "'s' in sqlite:///x.db")
    assert str(err.value) == (f"tune.search_space.model.dense_units: study 's' in "
                              f"sqlite:///x.db {message}, or start a new study with another "
                              f"tune.study_name")


def test_the_hand_off_takes_the_best_trial_inside_a_narrowed_range(tmp_path, smoke_data,
                                                                   tracking, capsys):
    """The learning rate's range was narrowed after trial 0, the best, ran outside it."""
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=2",
                   "tune.study_name=narrowed")
    study = optuna.create_study(study_name="narrowed", storage=cfg.tune.storage)
    study.add_trial(old_trial(0.5, 5e-3, 128))
    study.add_trial(old_trial(0.9, 1e-3, 256))
    out = tune(cfg)
    assert out["new_trials"] == [] and out["best_trial"] == 1
    assert out["best_params"] == {"optimizer.lr": 1e-3, "batch_size": 256}
    printed = capsys.readouterr().out
    assert ("note: trial 0 (val_loss 0.5) is better than trial 1 (val_loss 0.9) but lies "
            "outside the current search space (optimizer.lr=0.005 not in [0.0001, 0.003]); "
            "the hand-off takes trial 1, the best inside it\n") in printed
    handoff = (tmp_path / "conf" / "tuned" / "cnn.yaml").read_text()
    assert "trial 1, val_loss 0.9" in handoff and "lr: 0.001" in handoff
    client, parents, _ = study_runs(tracking, "narrowed")
    assert parents[0].data.tags["best_trial"] == "1"
    assert parents[0].data.metrics["best_val_loss"] == 0.9


def test_no_hand_off_when_every_completed_trial_lies_outside_the_space(tmp_path, smoke_data,
                                                                       tracking):
    cfg = tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=1", "tune.study_name=out")
    study = optuna.create_study(study_name="out", storage=cfg.tune.storage)
    study.add_trial(old_trial(0.5, 5e-3, 128))
    with pytest.raises(LboError) as err:
        tune(cfg)
    assert str(err.value) == (
        "study out: none of its 1 completed trials lies in the current search space (trial 0: "
        "optimizer.lr=0.005 not in [0.0001, 0.003]), so no hand-off was written; rerun with a "
        "larger tune.n_trials")
    assert not (tmp_path / "conf" / "tuned" / "cnn.yaml").exists()
    _, parents, _ = study_runs(tracking, "out")
    assert [p.info.status for p in parents] == ["FINISHED"]


@pytest.mark.slow
def test_two_workers_share_one_study(tmp_path, smoke_data, tracking):
    args = [sys.executable, "-m", "lbo.tune", "hparams_search=cnn", "experiment=smoke",
            f"data.root={smoke_data.parent}", "trainer.limit_train_batches=5",
            "tune.n_trials=3", f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
            f"tune.handoff={tmp_path / 'tuned' / 'cnn.yaml'}", "tune.study_name=shared",
            f"logger.tracking_uri={tracking}"]
    # started together, as a job array would: both open the study and race for its MLflow run
    workers = [subprocess.Popen([*args, f"hydra.run.dir={tmp_path / w}"], text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE) for w in "ab"]
    outs = [w.communicate(timeout=300) for w in workers]
    assert [w.returncode for w in workers] == [0, 0], outs[0][1][-2000:] + outs[1][1][-2000:]
    ran = [out.count("\ntrial ") for out, _ in outs]
    study = optuna.load_study(study_name="shared", storage=f"sqlite:///{tmp_path / 'optuna.db'}")
    finished = study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
    assert sum(ran) == len(study.trials) == len(finished)
    assert len(finished) == 3  # trials are claimed under the study's lock: no overshoot
    assert len({tuple(sorted(t.params.items())) for t in finished}) == len(finished)
    client, parents, children = study_runs(tracking, "shared")
    assert len(parents) == 1 and len(children) == len(finished)


@pytest.mark.slow
def test_cli_tunes_the_lstm_and_prints_the_hand_off_last(tmp_path, smoke_data, tracking):
    handoff = tmp_path / "tuned" / "lstm.yaml"
    res = cli("lbo.tune", "hparams_search=lstm", "experiment=smoke",
              f"data.root={smoke_data.parent}", "trainer.limit_train_batches=5",
              "tune.n_trials=1", f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
              f"tune.handoff={handoff}", f"logger.tracking_uri={tracking}",
              f"hydra.run.dir={tmp_path / 'run'}")
    assert res.returncode == 0, res.stderr[-3000:]
    lines = res.stdout.strip().splitlines()
    assert lines[0].startswith("study lstm-smoke-N20 in sqlite:///")
    assert lines[1].startswith("trial   0  val_loss")
    assert lines[-1] == f"tuned: {handoff}"
    cfg = compose_cfg("train", ["model=lstm", "+tuned=lstm",
                                f"hydra.searchpath=[file://{tmp_path}]"])
    assert len(cfg.model.hidden_sizes) == 4  # a list choice comes back as a list


# --- pieces -----------------------------------------------------------------------------------


def test_trials_never_see_the_test_set(tmp_path, smoke_data, tracking):
    cfg = tune_cfg(tmp_path, smoke_data, tracking, search="lstm")
    trial = trial_config(cfg, {"optimizer.lr": 0.5, "model.hidden_sizes": [4, 8, 16, 16]}, 7,
                         "s", tmp_path / "out")
    targets = [c["_target_"] for c in trial.callbacks.values()]
    assert "lbo.learn.callbacks.Evaluation" not in targets
    assert "lbo.learn.callbacks.Evaluation" in [c["_target_"] for c in cfg.callbacks.values()]
    assert trial.optimizer.lr == 0.5 and list(trial.model.hidden_sizes) == [4, 8, 16, 16]
    assert trial.output_dir == str(tmp_path / "out" / "s" / "trial_007")
    other = trial_config(cfg, {}, 7, "../cnn/x y", tmp_path / "out")  # one folder, never above
    assert other.output_dir == str(tmp_path / "out" / "_cnn_x_y" / "trial_007")
    assert "tune" not in trial and cfg.optimizer.lr == 0.001  # the study's config is untouched
    # nor does a trial keep ONNX graphs for lbo.observe (15 s for a window filter's)
    assert trial.keep_onnx is False and cfg.get("keep_onnx", True) is True
    # by type, not by name: a subclass of the evaluation callback under another name is
    # dropped too; a target that cannot be imported is one line
    with open_dict(cfg):
        cfg.callbacks.mine = {"_target_": "helpers.training.RenamedEvaluation"}
    assert "mine" not in trial_config(cfg, {}, 8, "s", tmp_path / "out").callbacks
    with open_dict(cfg):
        cfg.callbacks.mine = {"_target_": "no_such_package.Callback"}
    with pytest.raises(LboError, match=r"^_target_ 'no_such_package.Callback' cannot be "
                                       r"imported \(\w+\)$"):
        trial_config(cfg, {}, 8, "s", tmp_path / "out")


def test_list_choices_are_stored_as_text_and_decoded(tmp_path, smoke_data, tracking):
    space = {p.key: p for p in search_space(tune_cfg(tmp_path, smoke_data, tracking,
                                                     search="lstm"))}
    widths = space["model.hidden_sizes"]
    assert "[8, 16, 32, 32]" in widths.labels
    assert widths.suggest(optuna.trial.FixedTrial({"model.hidden_sizes": "[8, 16, 32, 32]"})) \
        == [8, 16, 32, 32]


TUNED = {  # inside each search space, and none of them training's default
    "cnn": {"optimizer.lr": 0.00237, "optimizer.weight_decay": 1e-5, "batch_size": 512,
            "model.conv_channels": 24, "model.feature_channels": 8, "model.dense_units": 181},
    "lstm": {"optimizer.lr": 0.0042, "optimizer.weight_decay": 1e-6, "batch_size": 64,
             "model.hidden_sizes": "[32, 64, 128, 128]", "model.dense_units": 45}}


@pytest.mark.parametrize(("search", "where"), [("cnn", "conf"), ("lstm", "elsewhere")])
def test_the_training_line_of_a_hand_off_composes_its_tuned_values(search, where, tmp_path):
    """The training line a hand-off carries (as tune prints it) composes, as written, into a
    training config for each window that holds the tuned settings and passes training's check:
    from conf/tuned/ (the default) with no search path, from any other folder with the one the
    line names."""
    import contextlib
    import shlex
    import uuid

    from omegaconf import OmegaConf

    from lbo.tuning.handoff import write_handoff

    folder = CONF_DIR / "tuned" if where == "conf" else tmp_path / "tuned"
    made = not folder.exists()
    path = folder / f"test_{uuid.uuid4().hex[:12]}.yaml"  # never a user's own <model>.yaml
    cfg = compose_cfg("tune", [f"hparams_search={search}", f"tune.handoff={path}"])
    space = search_space(cfg)
    stored = TUNED[search]
    assert {p.key for p in space} == set(stored)
    study = optuna.create_study(study_name="handoff")
    study.add_trial(optuna.trial.create_trial(
        params=stored, distributions={p.key: p.distribution() for p in space}, value=0.25))
    wanted = {p.key: p.decode(stored[p.key]) for p in space}
    untuned = compose_cfg("train", [f"model={search}"])
    assert all(OmegaConf.select(untuned, k) != v for k, v in wanted.items())
    try:
        write_handoff(cfg, study, space, "sqlite:///optuna.db")
        use = [line for line in path.read_text().splitlines() if line.startswith("# Use: ")]
        assert len(use) == 1
        words = shlex.split(use[0].removeprefix("# Use: "))
        assert words[:4] == ["python", "-m", "lbo.train", "-m"]
        overrides = [w for w in words[4:] if not w.startswith("window=")]
        sweep = [w for w in words[4:] if w.startswith("window=")]
        assert sweep == ["window=20,40,60,80"]  # the paper's windows, all from the one study
        assert any(w.startswith("hydra.searchpath=") for w in overrides) == (where != "conf")
        for window in (20, 40, 60, 80):
            trained = compose_cfg("train", [*overrides, f"window={window}"])
            assert trained.model.window == window and trained.model.name == search
            assert {k: OmegaConf.select(trained, k) for k in wanted} == wanted
            check(trained)
        if where != "conf":  # without its search path, Hydra would read +tuned=<name> as a
            # plain value and silently train with the defaults
            bare = [w for w in overrides if not w.startswith("hydra.searchpath=")]
            lost = compose_cfg("train", bare)
            assert {k: OmegaConf.select(lost, k) for k in wanted} == \
                {k: OmegaConf.select(untuned, k) for k in wanted}
    finally:
        path.unlink(missing_ok=True)
        if made:
            with contextlib.suppress(OSError):  # another test's hand-off may be there too
                folder.rmdir()


def test_the_sampler_repeats_nothing_when_resumed_or_shared():
    def objective(trial):
        return (trial.suggest_float("x", -1, 1) - 0.3) ** 2 + trial.suggest_int("n", 0, 9) / 10

    def study():
        return optuna.create_study(sampler=TrialSeededTPESampler(seed=0, n_startup_trials=3))

    whole = study()
    whole.optimize(objective, n_trials=6)
    resumed = study()
    resumed.optimize(objective, n_trials=3)
    resumed.sampler = TrialSeededTPESampler(seed=0, n_startup_trials=3)  # a new process
    resumed.optimize(objective, n_trials=3)
    assert [t.params for t in resumed.trials] == [t.params for t in whole.trials]
    assert len({t.params["x"] for t in whole.trials}) == 6


# --- bad input --------------------------------------------------------------------------------


@pytest.mark.parametrize("overrides, message", [
    ([], "tune.search_space is empty: choose a search with hparams_search=cnn"),
    (["tune.n_trials=0"], "tune.n_trials must be an integer >= 1, got 0"),
    (["tune.timeout=0"], "tune.timeout must be a number of seconds > 0"),
    (["tune.storage=sqlite:////nonexistent/lbo/optuna.db"],
     "tune.storage: cannot open sqlite:////nonexistent/lbo/optuna.db"),
    (["tune.storage=postgresql://lbo:secret@127.0.0.1:9/lbo"],
     r"tune.storage: cannot open postgresql://lbo:\*\*\*@127.0.0.1:9/lbo"),
    (["tune.storage=optuna.db"], "tune.storage: 'optuna.db' is not a database URL"),
    (["tune.storage=postgresql//lbo:secret@127.0.0.1/lbo"],
     r"^tune.storage: 'postgresql//lbo:\*\*\*@127.0.0.1/lbo' is not a database URL"),
    (["tune.storage='postgresql://lbo@127.0.0.1:9/lbo?password=secret'"],
     r"^tune.storage: cannot open postgresql://lbo@127.0.0.1:9/lbo\?password=\*\*\* "),
    (["tune.study_name='it\\'s \"x\"'"],
     r"^tune.study_name must be a name without both quote kinds \(' and \"\), which no "
     r"MLflow filter can hold, got 'it\\'s \"x\"'$"),
    (["model=lstm"], "tune.search_space.model.conv_channels: 'conv_channels' is not a "
                     "parameter of model 'lstm'; accepted: hidden_sizes"),
    (["+tune.search_space.optimizer.betas={type:float,low:0.5,high:0.9}"],
     "tune.search_space.optimizer.betas: no key 'optimizer.betas' in the training config"),
    (["+tune.search_space.window={type:int,low:20,high:80}"],
     "tune.search_space.window: 'window' is not a hyperparameter"),
    (["tune.search_space.batch_size.type=gaussian"],
     r"tune.search_space.batch_size must be \{type: float\|int\|categorical"),
    (["tune.search_space.optimizer.lr.low=0"],
     "tune.search_space.optimizer.lr.low must be > 0 on a log scale"),
    (["+tune.search_space.optimizer.lr.lg=true"], "unknown field 'lg' for a float distribution"),
    (["tune.pruner._target_=optuna.pruners.MedianPrunr"],
     "tune.pruner: cannot build 'optuna.pruners.MedianPrunr'"),
])
def test_bad_study_input_is_one_line_before_any_work(tmp_path, smoke_data, tracking, overrides,
                                                     message):
    own = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = tune_cfg(tmp_path, smoke_data, own, *overrides, search="cnn" if overrides else None)
    with pytest.raises(LboError, match=message) as err:
        tune(cfg)
    assert "\n" not in str(err.value) and "secret" not in str(err.value)
    assert list(tmp_path.iterdir()) == []  # no study, no MLflow store, no output


def test_an_unknown_search_is_listed_by_hydra():
    with pytest.raises(MissingConfigException, match="hparams_search/gru") as err:
        compose_cfg("tune", ["hparams_search=gru"])
    assert "cnn" in str(err.value.options) and "lstm" in str(err.value.options)


def test_locks_live_beside_the_database_not_in_the_temp_folder(tmp_path, smoke_data, tracking):
    import glob
    import tempfile

    before = set(glob.glob(f"{tempfile.gettempdir()}/lbo-*.lock"))
    tune(tune_cfg(tmp_path, smoke_data, tracking, "tune.n_trials=1", "tune.study_name=locks"))
    assert set(glob.glob(f"{tempfile.gettempdir()}/lbo-*.lock")) == before
    assert list(tmp_path.glob("optuna.db*.lock"))  # the study's and the store's, with the db


@pytest.mark.parametrize("hook", ["on_train_epoch_start", "on_train_batch_end",
                                  "on_validation_batch_end"])
def test_a_recorded_ctrl_c_stops_the_trial_at_each_safe_point(hook):
    """The first Ctrl-C is only recorded; the trial stops at the next epoch start or batch end
    (the epoch-start hook was once left behind, dead, in tune.py)."""
    from lbo.tuning.callbacks import Interrupts

    interrupts = Interrupts()
    getattr(interrupts, hook)(None, None)  # nothing recorded: goes on
    interrupts._on_signal(2, None)
    with pytest.raises(KeyboardInterrupt):
        getattr(interrupts, hook)(None, None)
