"""The SLURM path for real (``hydra/launcher=submitit_slurm``, ``make reproduce
LAUNCHER=submitit_slurm``): a one-node SLURM cluster started here (tests/helpers/slurm.py) and an
MLflow tracking server (tests/helpers/servers.py), both on 127.0.0.1, both stopped when the tests
end, pass or fail. ``make slurm-check`` runs this file.

Each job is checked to have ended as a SLURM job, from the cluster's job completion log."""

from __future__ import annotations

import os
import pickle
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import mlflow
import pytest

from helpers import one_line_error
from helpers.servers import mlflow_server
from helpers.slurm import NODE, PARTITION, Slurm, slurm_cluster
from lbo.core.errors import LboError

REPO = Path(__file__).resolve().parents[1]
SLURM = ["hydra/launcher=submitit_slurm", f"hydra.launcher.partition={PARTITION}",
         "hydra.launcher.cpus_per_task=1", "hydra.launcher.timeout_min=20"]
#: a smoke run's budget, cut to what shows it trains (seconds a job)
SHORT = ["experiment=smoke", "trainer.max_epochs=1", "trainer.limit_train_batches=5"]


# --- without a cluster ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["submitit_slurm", "submitit_local"])
def test_a_submitit_launcher_is_built_as_lbos(name):
    """Readied (as every lbo command readies the launcher its command line names), a config
    that names the plugin's launcher builds lbo's subclass of it; the config is the plugin's."""
    from hydra import compose, initialize_config_dir
    from hydra.core.plugins import Plugins

    from lbo.core import launchers
    from lbo.core.cli import launcher_context, ready_launcher
    from lbo.core.paths import CONF_DIR

    ready_launcher(name)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", [f"hydra/launcher={name}"], return_hydra_config=True)
        built = Plugins.instance().instantiate_launcher(
            hydra_context=launcher_context(cfg), task_function=lambda c: None, config=cfg)
    kind = "SlurmLauncher" if name == "submitit_slurm" else "LocalLauncher"
    assert cfg.hydra.launcher._target_ == f"{launchers.PLUGIN}.{kind}"
    assert type(built) is getattr(launchers, kind)
    # the plugin's class (Hydra's plugin scan may have loaded its module afresh: by name)
    assert [f"{c.__module__}.{c.__name__}" for c in type(built).__mro__[2:4]] == [
        f"{launchers.PLUGIN}.{kind}", f"{launchers.PLUGIN}.BaseSubmititLauncher"]


def test_a_jobs_error_goes_back_to_its_submitter_in_one_piece(monkeypatch, capsys):
    """In a launched job, a refusal is printed to the job's log and handed back (it pickles,
    as submitit sends it); elsewhere it is the usual one line and exit code 2."""
    from lbo.core import launchers
    from lbo.core.cli import fail_job

    with pytest.raises(SystemExit) as ended:
        fail_job(LboError("window: must be >= 4, got 2"))
    assert ended.value.code == 2
    assert capsys.readouterr().err == "error: window: must be >= 4, got 2\n"
    monkeypatch.setattr(launchers, "current_job", "SLURM job 7_1 on node-3")
    with pytest.raises(launchers.JobFailed) as raised:
        fail_job(LboError("tracking_uri: postgresql://lbo:secret@db/x is down"))
    assert capsys.readouterr().err == "error: tracking_uri: postgresql://lbo:***@db/x is down\n"
    back = pickle.loads(pickle.dumps(raised.value))
    assert isinstance(back, LboError)
    assert back.line() == ("tracking_uri: postgresql://lbo:***@db/x is down "
                           "(SLURM job 7_1 on node-3)")


def test_a_job_that_ended_without_a_result_is_one_line():
    from submitit.core.utils import UncompletedJobError

    from lbo.core.launchers import _uncompleted

    error = UncompletedJobError(
        "Job 12_1 (task: 0) with path /s/.submitit/12_1/12_1_0_result.pkl\n"
        "has not produced any output (state: CANCELLED by 0)\nError stream produced:\n"
        "----------------------------------------\nslurmstepd: error: *** JOB 14 CANCELLED")
    assert _uncompleted(error, "slurm") == (
        "SLURM job 12_1 ended without a result (state: CANCELLED by 0); its log: "
        "/s/.submitit/12_1/12_1_0_log.err. A rerun of the same command with resume=true reuses "
        "the runs that finished and continues a killed one from its last checkpoint")
    assert _uncompleted(UncompletedJobError("something else\nmore"), "slurm") == "something else"


def test_a_job_given_cpus_runs_that_many_threads(monkeypatch):
    """cpus_per_task=N: the job's intra-op threads are N (OMP_NUM_THREADS, unless set)."""
    from hydra.core.utils import JobReturn

    from lbo.core import launchers

    seen = {}

    class Base:
        def __call__(self, *args):
            seen["threads"] = os.environ.get("OMP_NUM_THREADS")
            return JobReturn()

    class Launcher(launchers._Lbo, Base):
        _EXECUTOR = "slurm"

    monkeypatch.setattr(launchers, "_job_name", lambda executor: "SLURM job 1_0 on n")
    monkeypatch.setattr(launchers, "current_job", None)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "3")
    import torch

    threads = torch.get_num_threads()
    try:
        Launcher()()
        assert seen["threads"] == "3" and torch.get_num_threads() == 3
        assert launchers.current_job == "SLURM job 1_0 on n"
        monkeypatch.setenv("OMP_NUM_THREADS", "1")  # set by the user: kept
        Launcher()()
        assert seen["threads"] == "1"
    finally:
        torch.set_num_threads(threads)


@pytest.mark.slow
def test_a_refused_job_of_submitit_local_ends_the_sweep_in_its_line(tmp_path):
    """hydra/launcher=submitit_local (no cluster): each job refuses max_epochs=0 in its log;
    the sweep ends in that line, naming a job, exit code 2, no traceback."""
    sweep = tmp_path / "sweep"
    res = subprocess.run([sys.executable, "-m", "lbo.train", "-m", "hydra/launcher=submitit_local",
                          "seed=0,1", "trainer.max_epochs=0", f"hydra.sweep.dir={sweep}"],
                         capture_output=True, text=True, timeout=300, cwd=REPO,
                         env={**os.environ,
                              "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    line = one_line_error(res, "error: trainer.max_epochs must be an integer >= 1, got 0 "
                               "(submitit job ")
    job = re.search(r"\(submitit job (\S+)\)$", line)[1]  # a local job's id is its pid
    assert (sweep / ".submitit" / job / f"{job}_0_log.err").read_text().strip().endswith(
        "error: trainer.max_epochs must be an integer >= 1, got 0")
    assert not (tmp_path / "mlflow.db").exists()


# --- a one-node SLURM cluster ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def unmounted():
    """A folder this machine holds that the cluster's node does not reach."""
    folder = Path(tempfile.mkdtemp(prefix="lbo-shared-"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster(unmounted):
    with slurm_cluster(unmounted=unmounted) as c:
        yield c


@pytest.fixture(scope="module")
def server():
    with mlflow_server() as s:
        yield s


def submit(cluster: Slurm, server, *args: str, env: dict[str, str] | None = None,
           timeout: float = 420) -> subprocess.CompletedProcess:
    """``python -m lbo.train -m <args>`` through SLURM, logging to ``server``. The jobs get
    no OMP_NUM_THREADS: lbo's launcher gives them cpus_per_task threads."""
    return subprocess.run([sys.executable, "-m", "lbo.train", "-m", *SLURM, *args],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO,
                          env=environment(cluster, server, env))


def environment(cluster: Slurm, server, extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    return {**env, **cluster.env, "MLFLOW_TRACKING_URI": server.url, **(extra or {})}


def runs_under(server, folder: Path) -> list:
    """The MLflow runs whose output folder lies under ``folder``."""
    client = mlflow.MlflowClient(server.url)
    exp = client.get_experiment_by_name("lbo-smoke")
    found = client.search_runs([exp.experiment_id]) if exp else []
    return [r for r in found if r.data.params.get("output_dir", "").startswith(str(folder))]


def sweep_jobs(cluster: Slurm, sweep: Path) -> dict[str, dict[str, str]]:
    """The SLURM jobs of the sweep in ``sweep`` (submitit's folders there), as they ended."""
    cluster.wait_empty()
    ids = sorted(p.parent.name for p in (sweep / ".submitit").glob("*/*_submitted.pkl"))
    ended = cluster.ended()
    assert ids and all(i in ended for i in ids), (ids, list(ended), cluster.logs())
    return {i: ended[i] for i in ids}


def job_log(sweep: Path, job: str, stream: str = "out") -> str:
    return (sweep / ".submitit" / job / f"{job}_0_log.{stream}").read_text()


@pytest.mark.slow
def test_a_sweep_runs_as_slurm_jobs_and_a_rerun_reuses_its_runs(cluster, server, smoke_data,
                                                                 tmp_path):
    """``python -m lbo.train -m model=cnn,lstm experiment=smoke hydra/launcher=submitit_slurm``:
    each observer a SLURM job, each logging a finished run to the server; the same command
    again reuses both runs (two more SLURM jobs, no new run)."""
    args = ["model=cnn,lstm", *SHORT, f"data.root={smoke_data.parent}", "resume=true"]
    first, again = tmp_path / "first", tmp_path / "again"
    start = time.perf_counter()
    res = submit(cluster, server, *args, f"hydra.sweep.dir={first}")
    print(f"sweep of 2 SLURM jobs: {time.perf_counter() - start:.1f} s")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:] + cluster.logs()
    assert "Submitit 'slurm' sweep output dir" in res.stdout
    jobs = sweep_jobs(cluster, first)
    assert len(jobs) == 2
    for job, ended in jobs.items():
        assert (ended["JobState"], ended["ExitCode"], ended["NodeList"], ended["Partition"],
                ended["Name"]) == ("COMPLETED", "0:0", NODE, PARTITION, "train"), ended
        assert "trained " in job_log(first, job)
    runs = runs_under(server, first)
    assert sorted(r.info.run_name for r in runs) == ["cnn-N20", "lstm-N20"]
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert all(r.info.artifact_uri.startswith("mlflow-artifacts:") for r in runs)  # the server's

    start = time.perf_counter()
    res = submit(cluster, server, *args, f"hydra.sweep.dir={again}")
    print(f"the same sweep again: {time.perf_counter() - start:.1f} s")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    rerun = sweep_jobs(cluster, again)
    assert len(rerun) == 2 and not set(rerun) & set(jobs)
    assert {j["JobState"] for j in rerun.values()} == {"COMPLETED"}
    reused = sorted(m for job in rerun for m in re.findall(r"reusing finished run (\w+)",
                                                           job_log(again, job)))
    assert reused == sorted(r.info.run_id for r in runs)
    assert runs_under(server, again) == []  # no run of its own
    assert len(runs_under(server, first)) == 2


@pytest.mark.slow
def test_a_job_cancelled_mid_training_is_continued_by_the_rerun(cluster, server, smoke_data,
                                                               tmp_path):
    """scancel a job once its first epoch's checkpoint is written: the sweep ends in one line
    naming the cancelled job; the same command again continues its run from that
    checkpoint, to a finished run, the only one of its config."""
    args = ["model=cnn", "experiment=smoke", "trainer.max_epochs=6", "seed=7",
            f"data.root={smoke_data.parent}", "resume=true"]
    killed, again = tmp_path / "killed", tmp_path / "again"
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "lbo.train", "-m", *SLURM, *args,
                             f"hydra.sweep.dir={killed}"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO,
                            env=environment(cluster, server))
    try:
        last = killed / "0" / "checkpoints" / "last.ckpt"
        deadline = time.monotonic() + 300
        while not last.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert last.exists(), "no epoch ended within 300 s" + cluster.logs()
        running = [j["id"] for j in cluster.queue() if j["state"] == "RUNNING"]
        assert len(running) == 1, cluster.queue()
        print(f"first epoch's checkpoint: {time.perf_counter() - start:.1f} s")
        cluster.command("scancel", running[0])
        cancelled = time.perf_counter()
        out, err = proc.communicate(timeout=180)
        print(f"the sweep's end {time.perf_counter() - cancelled:.1f} s after scancel: "
              f"{err.strip()}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    line = one_line_error(subprocess.CompletedProcess(proc.args, proc.returncode, out, err),
                          "ended without a result (state: CANCELLED", "resume=true")
    job = next(iter(sweep_jobs(cluster, killed)))
    assert f"SLURM job {job} " in line
    assert cluster.ended()[job]["JobState"] == "CANCELLED"
    [run] = runs_under(server, killed)
    assert run.info.status != "FINISHED"

    start = time.perf_counter()
    res = submit(cluster, server, *args, f"hydra.sweep.dir={again}")
    print(f"the rerun, continuing it: {time.perf_counter() - start:.1f} s")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    [rerun] = sweep_jobs(cluster, again).values()
    assert rerun["JobState"] == "COMPLETED"
    log = job_log(again, next(iter(sweep_jobs(cluster, again))))
    assert f"resuming the killed run {run.info.run_id} (same config) from {last}" in log
    [done] = runs_under(server, killed)  # continued in its own folder: the same run
    assert done.info.run_id == run.info.run_id and done.info.status == "FINISHED"
    assert runs_under(server, again) == []
    history = mlflow.MlflowClient(server.url).get_metric_history(run.info.run_id, "epoch")
    assert max(m.value for m in history) >= 1  # it went on past the epoch it was killed in


@pytest.mark.slow
def test_a_job_whose_node_cannot_reach_the_data_folder_fails_in_one_line(
        cluster, server, smoke_data, unmounted, tmp_path):
    """The data set lies in a folder that this machine holds and the node does not (a shared
    file system the node lacks): the job fails in lbo's one line, in its log and as the
    sweep's own error, naming the job; no run is left behind."""
    shared = unmounted / "data"
    shutil.copytree(smoke_data, shared / smoke_data.name)
    assert (shared / smoke_data.name / "train.parquet").is_file()  # here, not on the node
    sweep = tmp_path / "sweep"
    start = time.perf_counter()
    res = submit(cluster, server, "model=cnn", *SHORT, f"data.root={shared}",
                 f"hydra.sweep.dir={sweep}")
    print(f"{time.perf_counter() - start:.1f} s: {res.stderr.strip()}")
    [(job, ended)] = sweep_jobs(cluster, sweep).items()
    line = one_line_error(res, f"(SLURM job {job} on {NODE})")
    assert line == f"error: {shared}: Read-only file system (SLURM job {job} on {NODE})"
    assert f"error: {shared}: Read-only file system\n" in job_log(sweep, job, "err")
    assert ended["NodeList"] == NODE
    assert runs_under(server, sweep) == []


@pytest.mark.slow
def test_make_reproduce_through_slurm_and_again(cluster, server, smoke_data, tmp_path):
    """``make reproduce SCALE=smoke LAUNCHER=submitit_slurm``: its train stage's observers are
    SLURM jobs, their runs, artifacts and the report on the server; run again, it reuses every
    run and queues no job. The study's files go to a folder of its own (LBO_ROOT), where the
    smoke data sets are already (the data stage reuses them). The study is cut to the CNN at
    N=20 (``ARGS``): its three jobs (the paper's observer, the robust one, the paper's
    protocol) take each kind of job through SLURM; the whole smoke study is
    test_reproduce's."""
    root = tmp_path / "root"
    root.mkdir()
    (root / "conf").symlink_to(REPO / "conf")
    shutil.copytree(smoke_data, root / "data" / smoke_data.name)
    env = environment(cluster, server, {"LBO_ROOT": str(root), "OMP_NUM_THREADS": "1"})
    # -o: never reinstall .venv in a test (make test has installed it)
    make = ["make", "-s", "-o", ".venv/.installed", "reproduce", "SCALE=smoke",
            "LAUNCHER=submitit_slurm", "ARGS=models=[cnn] windows=[20]"]
    start = time.perf_counter()
    res = subprocess.run(make, capture_output=True, text=True, cwd=REPO, env=env, timeout=900)
    print(f"make reproduce SCALE=smoke: {time.perf_counter() - start:.1f} s")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "through hydra/launcher=submitit_slurm" in res.stdout
    assert "reused cached data sets 'smoke'" in res.stdout
    report = root / "reports" / "smoke"
    assert (report / "report.md").is_file()
    jobs = sweep_jobs(cluster, report / "runs")
    assert len(jobs) == 3  # the CNN, the robust observer, the paper's protocol
    assert {(j["JobState"], j["NodeList"]) for j in jobs.values()} == {("COMPLETED", NODE)}
    runs = runs_under(server, report / "runs")
    assert len(runs) == 3 and {r.info.status for r in runs} == {"FINISHED"}
    assert sorted(r.info.run_name for r in runs) == ["cnn-N20", "literal-cnn-N20",
                                                     "robust-filternet-N100"]
    assert len(list((server.folder / "artifacts").rglob("best.ckpt"))) >= 3

    before = set(cluster.ended())
    start = time.perf_counter()
    res = subprocess.run(make, capture_output=True, text=True, cwd=REPO, env=env, timeout=600)
    print(f"... and again: {time.perf_counter() - start:.1f} s")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "<== [3/5] train: reused" in res.stdout
    assert set(cluster.ended()) == before and not cluster.queue()  # no job queued
    assert sorted(r.info.run_id for r in runs_under(server, report / "runs")) == \
        sorted(r.info.run_id for r in runs)


@pytest.mark.slow
def test_the_cluster_is_gone_once_its_block_ends(tmp_path):
    """Every process the cluster started, and its folder, are gone when its block ends, also
    when the test in it fails."""
    class Failed(Exception):
        pass

    nap = f"{300 + os.getpid() % 1000 / 1000:.3f}"  # a command line no other process has

    with pytest.raises(Failed):
        with slurm_cluster() as c:
            folder, conf = c.folder, c.conf
            res = c.command("sbatch", "--wrap", f"srun sleep {nap}", "-o", str(tmp_path / "o"))
            assert res.stdout.startswith("Submitted batch job")
            deadline = time.monotonic() + 30
            while not any(j["state"] == "RUNNING" for j in c.queue()):
                assert time.monotonic() < deadline, c.queue()
                time.sleep(0.2)
            raise Failed
    assert not folder.exists()
    from helpers.slurm import _stragglers

    assert _stragglers(conf) == []
    alive = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
    assert str(folder) not in alive and f"sleep {nap}" not in alive
