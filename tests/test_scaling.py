"""Scaling out, against the real engines: Hydra's joblib launcher, an MLflow tracking server and
Optuna on PostgreSQL. Every server is started by the test itself (tests/helpers/servers.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import mlflow
import numpy as np
import optuna
import pandas as pd
import pytest
from omegaconf import open_dict

from helpers import SWEEP_BUDGET, cli, compose_cfg, store_client, train_cfg
from helpers.servers import PG_PASSWORD, free_port, mlflow_server, postgres
from lbo.core.cli import check_launcher, launcher_from_argv
from lbo.core.errors import LboError
from lbo.tuning.storage import MAX_CONNECTIONS

pytestmark = pytest.mark.usefixtures("one_torch_thread")
optuna.logging.set_verbosity(optuna.logging.WARNING)
SWEEP = ["model=cnn,lstm", "window=20,40"]


def finished_runs(uri: str) -> pd.DataFrame:
    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("lbo-smoke")
    found = client.search_runs([exp.experiment_id]) if exp else []
    return pd.DataFrame([{"name": r.info.run_name, "status": r.info.status,
                          "output": r.data.params.get("output_dir"),
                          **{k: v for k, v in r.data.metrics.items()
                             if k.startswith("test_nrmse")}} for r in found])


# --- launchers ----------------------------------------------------------------------------------


def test_the_launcher_named_on_the_command_line_is_found():
    assert launcher_from_argv(["-m", "model=cnn", "hydra/launcher=joblib"]) == "joblib"
    assert launcher_from_argv(["+hydra/launcher=basic", "window=20"]) == "basic"
    assert launcher_from_argv(["model=cnn"]) is None


@pytest.mark.parametrize(("launcher", "target", "says"), [
    ("basic", "hydra._internal.core_plugins.basic_launcher.BasicLauncher",  # Hydra's own
     "Launching 2 jobs locally"),
    ("joblib", "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher",
     "is launching 2 jobs")])  # installed by make install (lbo[launchers])
def test_an_installed_launcher_passes_the_check_and_launches_the_sweep(launcher, target, says,
                                                                       tmp_path):
    """The launcher check lets Hydra's own launcher and an installed plugin through: the sweep's
    jobs are launched by that launcher. Each job then stops at training's own check
    (max_epochs=0), in one line, so nothing trains."""
    from omegaconf import OmegaConf

    sweep = tmp_path / "sweep"
    # a process of its own: the jobs' lines come from joblib's workers, which write to the
    # process's stderr, and which joblib keeps for later sweeps with the environment they
    # started with
    res = cli("lbo.train", "-m", f"hydra/launcher={launcher}", "seed=0,1",
              "trainer.max_epochs=0", f"hydra.sweep.dir={sweep}",
              env={"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}, timeout=300,
              process=True)
    assert says in res.stdout, res.stdout[-2000:] + res.stderr[-2000:]
    assert "not installed" not in res.stderr
    assert res.returncode == 2
    assert res.stderr.strip().splitlines()[-1] == \
        "error: trainer.max_epochs must be an integer >= 1, got 0"
    # a job refused first may end the sweep before another job has written its files
    jobs = sorted(sweep.glob("*/.hydra/hydra.yaml"))
    assert jobs and all(OmegaConf.load(j).hydra.launcher._target_ == target for j in jobs)
    assert not (tmp_path / "mlflow.db").exists()  # refused before any run opened


RECLAIM = """
import os, sys
from lbo.core.cli import ready_launcher
if sys.argv[2] == "ready":
    ready_launcher("joblib")
from joblib.externals.loky.backend import resource_tracker
os.makedirs(sys.argv[1])
resource_tracker.register(sys.argv[1], "folder")  # left to the tracker, as a killed worker's
print("registered", flush=True)
"""


@pytest.mark.parametrize("how", ["plain", "ready"])
def test_a_joblib_sweep_ends_on_its_one_line_not_on_the_trackers_reclaims(how, tmp_path):
    """When a joblib sweep fails, joblib kills the jobs still running and loky's resource
    tracker reclaims what they held, after lbo's one-line error: readied for joblib, the
    tracker reclaims without a word; not readied, it warns (the control)."""
    held = tmp_path / "held"
    res = subprocess.run([sys.executable, "-c", RECLAIM, str(held), how], capture_output=True,
                         text=True, timeout=120, env={k: v for k, v in os.environ.items()
                                                      if k != "PYTHONWARNINGS"})
    assert res.stdout == "registered\n", res.stderr
    deadline = time.monotonic() + 30
    while held.exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not held.exists()  # reclaimed either way
    assert ("leaked folder objects" in res.stderr) == (how == "plain"), res.stderr


def test_a_missing_launcher_plugin_is_one_line_with_its_install_command(tmp_path):
    res = cli("lbo.train", "-m", "hydra/launcher=ray", "experiment=smoke",
              f"hydra.sweep.dir={tmp_path / 'sweep'}",
              env={"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    assert res.returncode == 2
    assert res.stderr.strip() == (
        "error: hydra/launcher=ray: the Hydra plugin hydra-ray-launcher is not installed "
        "(pip install hydra-ray-launcher, or make install, which installs lbo[launchers])")
    assert not (tmp_path / "sweep").exists() and not (tmp_path / "mlflow.db").exists()


def test_an_unreachable_tracking_server_is_one_line_and_starts_nothing(tmp_path):
    dead = f"http://127.0.0.1:{free_port()}"
    res = cli("lbo.train", "experiment=smoke", f"output_dir={tmp_path / 'out'}",
              env={"MLFLOW_TRACKING_URI": dead})
    assert res.returncode == 2, res.stderr[-2000:]
    assert res.stderr.strip() == (
        f"error: MLFLOW_TRACKING_URI: no MLflow tracking server answers at {dead} "
        "(ConnectionError); start one (make mlflow-server) or unset MLFLOW_TRACKING_URI")
    assert not (tmp_path / "out").exists()


def test_check_launcher_names_the_package_when_its_module_is_missing(monkeypatch):
    from lbo.core import cli

    monkeypatch.setitem(cli.LAUNCHERS, "joblib", ("hydra_plugins.not_here",
                                                       "hydra-joblib-launcher"))
    with pytest.raises(LboError, match=r"^hydra/launcher=joblib: the Hydra plugin "
                                       r"hydra-joblib-launcher is not installed \(pip install"):
        check_launcher("joblib")


def test_the_launcher_context_instantiates_the_launcher_a_config_names():
    """lbo's one use of a private Hydra module (its callbacks) builds what a launcher plugin
    is instantiated with: an ImportError or a changed signature fails here, not hours into
    make reproduce."""
    from hydra import compose, initialize_config_dir
    from hydra.core.plugins import Plugins
    from hydra.types import HydraContext

    from lbo.core.cli import launcher_context
    from lbo.core.paths import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", ["hydra/launcher=joblib"], return_hydra_config=True)
        context = launcher_context(cfg)
        launcher = Plugins.instance().instantiate_launcher(
            hydra_context=context, task_function=lambda c: None, config=cfg)
    assert isinstance(context, HydraContext)
    assert type(launcher).__name__ == "JoblibLauncher"


@pytest.mark.slow
def test_joblib_sweep_matches_the_serial_sweep(tmp_path, smoke_data, paper_sweep):
    """Four smoke jobs two at a time, each job's MLflow writes racing the others' on one SQLite
    file: four finished runs in four folders, with the numbers of the same four runs in the
    serial sweep (the paper's, run once for the test run: ``paper_sweep`` in conftest)."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    start = time.perf_counter()
    # a process of its own: joblib's workers write to the process's stderr (read for
    # "database is locked"), and joblib keeps them, with their environment, for later sweeps
    res = cli("lbo.train", "-m", *SWEEP, "experiment=smoke", *SWEEP_BUDGET,
              f"data.root={smoke_data.parent}", f"hydra.sweep.dir={tmp_path / 'sweep'}",
              "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
              env={"MLFLOW_TRACKING_URI": uri}, process=True)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "database is locked" not in res.stderr
    print(f"joblib: {time.perf_counter() - start:.1f} s")
    table = finished_runs(uri)
    assert len(table) == 4 and set(table["status"]) == {"FINISHED"}
    assert table["output"].nunique() == 4  # one folder, and one checkpoint, per job
    assert all(str(o).startswith(str(tmp_path / "sweep")) for o in table["output"])
    assert len(list((tmp_path / "sweep").glob("*/checkpoints/best*.ckpt"))) == 4
    joblib = table.set_index("name").drop(columns=["status", "output"]).sort_index()
    assert sorted(joblib.index) == ["cnn-N20", "cnn-N40", "lstm-N20", "lstm-N40"]
    assert paper_sweep["returncode"] == 0, paper_sweep["stderr"][-3000:]
    serial = finished_runs(paper_sweep["uri"]).set_index("name").loc[joblib.index]
    pd.testing.assert_frame_equal(joblib, serial.drop(columns=["status", "output"]), rtol=1e-6)


# --- an MLflow tracking server ------------------------------------------------------------------


def test_a_data_set_input_lost_to_a_racing_run_is_logged_again():
    """Two runs logging the same data set at once: the store's second insert fails on its
    unique key (the record exists by then), and log_input logs the input again; any other
    error, or the same one every time, is raised."""
    from mlflow.exceptions import MlflowException

    from lbo.tracking.runs import dataset_input, log_input

    class Store:
        def __init__(self, errors):
            self.errors, self.logged = list(errors), []

        def log_inputs(self, run_id, datasets):
            if self.errors:
                raise MlflowException(self.errors.pop(0))
            self.logged.append((run_id, datasets[0].dataset.digest))

    race = ("BAD_REQUEST: (sqlite3.IntegrityError) UNIQUE constraint failed: "
            "datasets.experiment_id, datasets.name, datasets.digest")
    store = Store([race])
    log_input(store, "r1", dataset_input("smoke", "a8c688af2968", "/data/smoke-a8c688af2968"))
    assert store.logged == [("r1", "a8c688af2968")]
    for errors in ([race] * 3, ["RESOURCE_DOES_NOT_EXIST: run r1"]):
        with pytest.raises(MlflowException):
            log_input(Store(errors), "r1", dataset_input("smoke", "a8", "/data"))


@pytest.fixture(scope="module")
def server():
    """One tracking server for this module's tests: each works in experiments and runs of
    its own (a server's start is seconds of the suite's time)."""
    with mlflow_server() as s:
        yield s


@pytest.mark.slow
def test_runs_started_together_all_log_their_data_set_on_a_server(server):
    """Eight runs log the same data set at the same moment through a real tracking server,
    in five experiments: each run has its input. (MlflowClient.log_inputs alone failed for 5
    of these 40 runs, on the store's unique key.)"""
    import threading

    from lbo.tracking.runs import dataset_input, log_input

    client = mlflow.MlflowClient(server.url)
    for k in range(5):
        exp = client.create_experiment(f"race-{k}")
        runs = [client.create_run(exp).info.run_id for _ in range(8)]
        start, failed = threading.Barrier(len(runs)), []

        def log(run_id, start=start, failed=failed):
            start.wait()
            try:
                log_input(client, run_id, dataset_input("smoke", "a8c688af2968", "/d/s"))
            except Exception as e:  # noqa: BLE001 - reported below
                failed.append(e)

        threads = [threading.Thread(target=log, args=(r,)) for r in runs]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert failed == []
        for r in runs:
            [used] = client.get_run(r).inputs.dataset_inputs
            assert used.dataset.digest == "a8c688af2968"


@pytest.mark.slow
def test_train_observe_export_and_tune_through_a_tracking_server(tmp_path, smoke_data, monkeypatch,
                                                        manoeuvre_csv, server):
    from lbo.serve.observer import Observer
    from lbo.train import train

    monkeypatch.setenv("MLFLOW_TRACKING_URI", server.url)
    out = train(train_cfg(tmp_path, smoke_data, "trainer.max_epochs=1",
                          "trainer.limit_train_batches=5"))
    client = mlflow.MlflowClient(server.url)
    run = client.get_run(out["run_id"])
    assert run.info.status == "FINISHED"
    assert {"val_loss", "test_nrmse_alpha_1"} <= set(run.data.metrics)
    assert run.info.artifact_uri.startswith("mlflow-artifacts:")  # stored by the server
    files = [a.path for a in client.list_artifacts(out["run_id"], "checkpoints")]
    assert files == ["checkpoints/best.ckpt"]
    assert list((server.folder / "artifacts").rglob("best.ckpt"))

    est = tmp_path / "est.csv"
    res = cli("lbo.observe", f"observer={out['run_id']}", f"input={manoeuvre_csv}",
              f"output={est}", env={"MLFLOW_TRACKING_URI": server.url})
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"observed: {est}" in res.stdout
    log = pd.read_csv(manoeuvre_csv).head(60)
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(), log[["V", "delta"]].to_numpy()
    remote = Observer.load(out["run_id"]).run(m, u)  # the checkpoint, through the server
    local = Observer.load(out["checkpoint"]).run(m, u)
    np.testing.assert_array_equal(remote[0], local[0])

    res = cli("lbo.export", f"observer={out['run_id']}", "register=lbo-served",
              f"out_dir={tmp_path / 'exports'}", env={"MLFLOW_TRACKING_URI": server.url})
    assert res.returncode == 0, res.stderr[-3000:]
    assert client.get_model_version("lbo-served", "1").run_id == out["run_id"]
    assert list((tmp_path / "exports").glob("*.onnx"))
    registered = Observer.load("models:/lbo-served/1").run(m, u)
    np.testing.assert_array_equal(registered[0], local[0])

    res = cli("lbo.tune", *tune_args(tmp_path, smoke_data,
                                     f"sqlite:///{tmp_path / 'optuna.db'}",
                                     "tune.n_trials=1", f"hydra.run.dir={tmp_path / 't'}"),
              env={"MLFLOW_TRACKING_URI": server.url})
    assert res.returncode == 0, res.stderr[-3000:]
    study = client.search_runs([run.info.experiment_id], "tags.optuna_role = 'study'")
    assert len(study) == 1 and study[0].info.status == "FINISHED"
    assert client.list_artifacts(study[0].info.run_id, "tuned")


@pytest.fixture
def manoeuvre_csv(tmp_path, manoeuvre):
    path = tmp_path / "log.csv"
    manoeuvre[["t", "x_m", "y_m", "psi_m", "V", "delta"]].to_csv(path, index=False)
    return path


# --- Optuna on PostgreSQL ---------------------------------------------------------------------


def tune_args(tmp_path, smoke_data, storage, *extra):
    return ["hparams_search=cnn", "experiment=smoke", f"data.root={smoke_data.parent}",
            "trainer.limit_train_batches=5", "tune.n_trials=4", f"tune.storage={storage}",
            f"tune.handoff={tmp_path / 'tuned' / 'cnn.yaml'}", "tune.study_name=pg",
            "tune.heartbeat_interval=1", "tune.grace_period=3",
            f"output_dir={tmp_path / 'trials'}", *extra]


#: Connections the test's own view of a study holds at most (Optuna's schema check takes two).
READER_CONNECTIONS = 2


def reader(storage: str) -> optuna.storages.RDBStorage:
    """The test's own view of a study on PostgreSQL, with at most READER_CONNECTIONS,
    named ``test``. (``optuna.load_study(storage=<url>)`` opens a new pool on every call:
    polled, it held dozens of connections until garbage collection, and the server ran out.)"""
    return optuna.storages.RDBStorage(storage, engine_kwargs={
        "pool_size": 1, "max_overflow": READER_CONNECTIONS - 1,
        "connect_args": {"application_name": "test"}})


@pytest.mark.slow
def test_workers_on_postgres_finish_exactly_n_trials_after_a_kill(tmp_path, smoke_data):
    """Two workers and the test on a server with just the connections they need: each worker
    holds at most MAX_CONNECTIONS at once (measured exactly, from the server's connection
    log), and none once it ended."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    env = {"MLFLOW_TRACKING_URI": uri}
    with postgres(max_connections=2 * MAX_CONNECTIONS + READER_CONNECTIONS,
                  superuser_reserved_connections=0) as pg:
        storage = pg.url()
        args = [sys.executable, "-m", "lbo.tune", *tune_args(tmp_path, smoke_data, storage)]
        workers = {w: subprocess.Popen([*args, f"hydra.run.dir={tmp_path / w}"], text=True,
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                       env={**os.environ, **env}) for w in "ab"}
        # kill worker a with SIGKILL while one of its trials runs
        victim, deadline, killed = workers["a"], time.monotonic() + 240, None
        view = None
        while killed is None and time.monotonic() < deadline and victim.poll() is None:
            time.sleep(0.2)
            try:
                view = view or reader(storage)
                study = optuna.load_study(study_name="pg", storage=view)
            except KeyError:  # not created yet
                continue
            for t in study.get_trials(states=(optuna.trial.TrialState.RUNNING,)):
                if t.user_attrs.get("worker", "").endswith(f":{victim.pid}"):
                    victim.send_signal(signal.SIGKILL)
                    killed = t.number
        assert killed is not None, "worker a finished before it could be killed mid-trial"
        victim.communicate(timeout=60)
        out_b, err_b = workers["b"].communicate(timeout=600)
        assert workers["b"].returncode == 0, err_b[-3000:]
        # worker a again: it finds what is missing, if anything, and stops at n_trials
        again = cli("lbo.tune", *tune_args(tmp_path, smoke_data, storage,
                                           f"hydra.run.dir={tmp_path / 'a2'}"), env=env)
        assert again.returncode == 0, again.stderr[-3000:]
        for text in (out_b, err_b, again.stdout, again.stderr):
            assert PG_PASSWORD not in text

        study = optuna.load_study(study_name="pg", storage=view or reader(storage))
        states = {t.number: t.state for t in study.trials}
        finished = [t for t in study.trials if t.state in (optuna.trial.TrialState.COMPLETE,
                                                           optuna.trial.TrialState.PRUNED)]
        assert len(finished) == 4
        assert states[killed] == optuna.trial.TrialState.FAIL
        assert len({tuple(sorted(t.params.items())) for t in finished}) == 4
        (view or reader(storage)).engine.dispose()
        held = pg.connections()
        workers_held = {app: c for app, c in held.items() if app.startswith("lbo.tune-")}
        print("connections (peak, open) per client:", held)
        assert len(workers_held) == 3  # a, b and a again
        assert all(peak <= MAX_CONNECTIONS and now == 0 for peak, now in workers_held.values())
    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("lbo-smoke")
    live = client.search_runs([exp.experiment_id], "attributes.status = 'RUNNING'")
    assert live == []  # the killed trial's run was closed FAILED, the study's FINISHED
    tags = [r.data.tags.get("optuna_storage", "") for r in client.search_runs(
        [exp.experiment_id], "tags.optuna_role = 'study'")]
    assert tags and all("***" in t and PG_PASSWORD not in t for t in tags)


@pytest.mark.slow
def test_tune_on_postgres_holds_few_connections_and_closes_them(tmp_path, smoke_data):
    """In one process (as reproduce runs its studies): at most MAX_CONNECTIONS at once, none
    left open after tune returns or raises; the password appears in nothing it logs."""
    from lbo.tune import tune

    tracking = f"sqlite:///{tmp_path / 'mlflow.db'}"
    with postgres() as pg:
        def cfg(name, *extra):
            return compose_cfg("tune", [*tune_args(tmp_path, smoke_data, pg.url(), *extra),
                                        "tune.n_trials=2", f"tune.study_name={name}",
                                        f"logger.tracking_uri={tracking}"])

        out = tune(cfg("inproc"))
        after_return = pg.connections()
        pruned = cfg("pruned", "tune.n_trials=1")
        with open_dict(pruned):  # prunes every trial at its first report: tune raises
            pruned.tune.pruner = {"_target_": "optuna.pruners.ThresholdPruner", "upper": 0.0}
        with pytest.raises(LboError, match="no trial has completed"):
            tune(pruned)
        after_error = pg.connections()
    print("connections (peak, open) per client:", after_error)
    assert sum(now for _, now in after_return.values()) == 0
    assert sum(now for _, now in after_error.values()) == 0
    assert after_error == {f"lbo.tune-{os.getpid()}": (after_error[f"lbo.tune-{os.getpid()}"][0],
                                                       0)}
    assert after_error[f"lbo.tune-{os.getpid()}"][0] <= MAX_CONNECTIONS

    parent = mlflow.MlflowClient(tracking).get_run(out["parent_run_id"]).data
    assert parent.params["storage"] == f"postgresql://lbo:***@127.0.0.1:{pg.port}/postgres"
    logged = [*parent.params.values(), *parent.tags.values(), out["handoff"].read_text()]
    assert not [v for v in logged if PG_PASSWORD in str(v)]
    assert "postgresql://lbo:***@" in out["handoff"].read_text()


@pytest.mark.slow
def test_a_wrong_postgres_password_is_one_line_and_leaves_no_run(tmp_path, smoke_data):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    with postgres() as pg:
        res = cli("lbo.tune", *tune_args(tmp_path, smoke_data, pg.url("not-the-password"),
                                         f"hydra.run.dir={tmp_path / 'run'}"),
                  env={"MLFLOW_TRACKING_URI": uri})
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "not-the-password" not in res.stderr
    assert lines[0].startswith(f"error: tune.storage: cannot open postgresql://lbo:***@"
                               f"127.0.0.1:{pg.port}/postgres (OperationalError: ")
    assert "password authentication failed" in lines[0]
    client = store_client(uri)
    exp = client.get_experiment_by_name("lbo-smoke")
    assert exp is None or client.search_runs([exp.experiment_id]) == []



@pytest.mark.slow
def test_reproduce_trains_through_the_launcher_and_resumes_without_duplicates(
        tmp_path, smoke_data, monkeypatch):
    """make reproduce LAUNCHER=joblib: the train stage hands its jobs (which differ in more
    than a grid: +tuned, the robust observer) to Hydra's joblib launcher; a second pass reuses
    every finished run and adds none."""
    from hydra import compose, initialize_config_dir

    from lbo.core.paths import CONF_DIR
    from lbo.reproduce import launch

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    base = [f"data.root={smoke_data.parent}", "trainer.max_epochs=1",
            "trainer.limit_train_batches=5", "resume=true"]
    jobs = {"cnn-N20": ["experiment=smoke", *base, "model=cnn", "window=20",
                        f"output_dir={tmp_path / 'cnn'}"],
            "robust": ["experiment=robust", *base, "data=smoke", "window=100", "batch_size=64",
                       "keep_onnx=false", f"output_dir={tmp_path / 'robust'}",
                       "logger.run_name=robust-filternet-N100"]}  # as make reproduce names it
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("reproduce", ["launcher=joblib", "jobs=2"])
        first = launch(cfg, list(jobs.values()), tmp_path / "runs", list(jobs))
        second = launch(cfg, list(jobs.values()), tmp_path / "runs", list(jobs))
    assert [r["name"] for r in first] == ["cnn-N20", "filternet-N100"]
    assert [r["reused"] for r in first] == [False, False]
    assert [r["reused"] for r in second] == [True, True]
    assert [r["run_id"] for r in second] == [r["run_id"] for r in first]
    # reused, the robust observer keeps its name (its run's is robust-filternet-N100)
    assert [r["name"] for r in second] == [r["name"] for r in first]
    assert (tmp_path / "runs" / "robust" / ".hydra" / "overrides.yaml").is_file()
    table = finished_runs(uri)
    assert len(table) == 2 and set(table["status"]) == {"FINISHED"}
