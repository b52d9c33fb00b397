import subprocess
import sys
import time
import warnings

import mlflow
import optuna
import pytest
from hydra.errors import MissingConfigException
from omegaconf import open_dict

from conftest import compose_cfg
from lbo.errors import LboError
from lbo.paths import CONF_DIR
from lbo.study_mlflow import StudyRun
from lbo.train import check
from lbo.tune import (
    TrialSeededTPESampler,
    open_storage,
    search_space,
    train_command,
    trial_config,
    tune,
)

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
    exp = client.get_experiment_by_name("lbo")
    found = client.search_runs([exp.experiment_id], f"tags.optuna_study = '{study_name}'")
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
    handoff = tmp_path / "conf" / "tuned" / "cnn.yaml"
    assert printed[-1] == f"tuned: {handoff}"
    assert "+tuned=cnn" in printed[-2] and "window=20,40,60,80" in printed[-2]

    # the hand-off composes into training for every window, and training accepts it
    best = again["best_params"]
    assert set(best) == {"optimizer.lr", "optimizer.weight_decay", "batch_size",
                         "model.conv_channels", "model.feature_channels", "model.dense_units"}
    cfg = compose_cfg("train", ["model=cnn", "+tuned=cnn", "window=60",
                                f"hydra.searchpath=[file://{tmp_path / 'conf'}]"])
    assert cfg.window == 60
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
    lr = dead.suggest_float("optimizer.lr", 1e-4, 1e-2, log=True)
    storage.record_heartbeat(dead._trial_id)
    client = mlflow.MlflowClient(tracking)
    exp = client.get_experiment_by_name("lbo") or client.get_experiment(client.create_experiment(
        "lbo", artifact_location=cfg.logger.artifact_location))
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
    res = subprocess.run(
        [sys.executable, "-m", "lbo.tune", "hparams_search=lstm", "experiment=smoke",
         f"data.root={smoke_data.parent}", "trainer.limit_train_batches=5", "tune.n_trials=1",
         f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}", f"tune.handoff={handoff}",
         f"logger.tracking_uri={tracking}", f"hydra.run.dir={tmp_path / 'run'}"],
        capture_output=True, text=True)
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
    assert "lbo.callbacks.Evaluation" not in targets
    assert "lbo.callbacks.Evaluation" in [c["_target_"] for c in cfg.callbacks.values()]
    assert trial.optimizer.lr == 0.5 and list(trial.model.hidden_sizes) == [4, 8, 16, 16]
    assert trial.output_dir == str(tmp_path / "out" / "trial_007")
    assert "tune" not in trial and cfg.optimizer.lr == 0.001  # the study's config is untouched


def test_list_choices_are_stored_as_text_and_decoded(tmp_path, smoke_data, tracking):
    space = {p.key: p for p in search_space(tune_cfg(tmp_path, smoke_data, tracking,
                                                     search="lstm"))}
    widths = space["model.hidden_sizes"]
    assert "[8, 16, 32, 32]" in widths.labels
    assert widths.suggest(optuna.trial.FixedTrial({"model.hidden_sizes": "[8, 16, 32, 32]"})) \
        == [8, 16, 32, 32]


def test_the_default_hand_off_needs_no_search_path(tmp_path):
    assert train_command("cnn", CONF_DIR / "tuned" / "cnn.yaml") == \
        "python -m lbo.train -m model=cnn +tuned=cnn window=20,40,60,80"
    assert train_command("lstm", tmp_path / "tuned" / "lstm.yaml").endswith(
        f"+tuned=lstm window=20,40,60,80 'hydra.searchpath=[file://{tmp_path}]'")


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
