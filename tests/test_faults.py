"""Faults a user meets: a killed run, absurd values, foreign files, late checks."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import mlflow
import numpy as np
import pytest
import torch

from helpers import cli, compose_cfg, kill_when_written
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer


def _train_args(tmp_path, smoke_data, out, *more):
    """``lbo.train``'s arguments; one intra-op thread in this process and in a subprocess
    alike, so that their runs compare to the bit."""
    return ["experiment=smoke", "resume=true", "threads=1", f"data.root={smoke_data.parent}",
            f"output_dir={out}", "trainer.max_epochs=4", "trainer.limit_train_batches=30",
            f"hydra.run.dir={tmp_path / 'hydra'}", *more]


def _train_cmd(tmp_path, smoke_data, out, *more):
    return [sys.executable, "-m", "lbo.train", *_train_args(tmp_path, smoke_data, out, *more)]


@pytest.mark.slow
@pytest.mark.parametrize("trained", [
    (), ("model=split_kalmannet", "features=frame", "window=40", "tbptt=10",
         "lr_schedule=cosine", "trainer.limit_train_batches=15")],  # a carried epoch: seconds
    ids=["windows", "carried"])
def test_a_killed_run_resumes_from_its_last_checkpoint_as_if_never_killed(tmp_path, smoke_data,
                                                                        monkeypatch, trained):
    """Killed in its third epoch and rerun: the run continues where its last checkpoint left
    it, with the random streams restored, and ends with the unbroken run's metrics; also
    trained carried (``tbptt``: the optimiser steps per chunk, the schedule by hand)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    # the unbroken run, in a store of its own (in this process: only the kill needs one)
    ref_env = {"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'ref.db'}"}
    ref = cli("lbo.train", *_train_args(tmp_path, smoke_data, tmp_path / "ref", *trained),
              env=ref_env)
    assert ref.returncode == 0, ref.stderr[-3000:]

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    env["MLFLOW_TRACKING_URI"] = uri
    out = tmp_path / "out"
    last = out / "checkpoints" / "last.ckpt"
    proc = subprocess.Popen(_train_cmd(tmp_path, smoke_data, out, *trained), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    watcher = kill_when_written(proc, last, times=2, delay=0.3)  # into the third epoch
    proc.wait(timeout=300)
    watcher.join()
    assert proc.returncode == -signal.SIGKILL and last.exists()
    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("lbo-smoke")
    (killed,) = client.search_runs([exp.experiment_id])
    assert killed.info.status == "RUNNING"
    assert len(client.get_metric_history(killed.info.run_id, "val_loss")) in (2, 3)

    # the rerun, from another folder, continues the killed run in its own folder
    rerun = cli("lbo.train", *_train_args(tmp_path, smoke_data, tmp_path / "elsewhere", *trained),
                env={"MLFLOW_TRACKING_URI": uri})
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert f"resuming the killed run {killed.info.run_id} (same config) from {last}" in \
        rerun.stdout
    (run,) = client.search_runs([exp.experiment_id], run_view_type=3)
    assert run.info.run_id == killed.info.run_id and run.info.status == "FINISHED"
    assert sorted(p.name for p in last.parent.glob("*.ckpt")) == ["best.ckpt", "last.ckpt"]
    # the same final metrics, to the last bit on the CPU, as the run that was never killed
    ref_client = mlflow.MlflowClient(ref_env["MLFLOW_TRACKING_URI"])
    (unbroken,) = ref_client.search_runs(
        [ref_client.get_experiment_by_name("lbo-smoke").experiment_id])
    tests = {k: v for k, v in run.data.metrics.items() if k.startswith("test_")}
    assert tests and tests == {k: v for k, v in unbroken.data.metrics.items()
                               if k.startswith("test_")}
    # an epoch validated just before the kill, whose checkpoint was not yet written, runs
    # again after it and logs its val_loss at the same step once more: the same value
    history: dict[int, list[float]] = {}
    for m in client.get_metric_history(run.info.run_id, "val_loss"):
        history.setdefault(m.step, []).append(m.value)
    assert all(len(set(v)) == 1 for v in history.values()), history
    assert sum(len(v) > 1 for v in history.values()) <= 1, history  # not trained from scratch
    want = {m.step: m.value for m in ref_client.get_metric_history(unbroken.info.run_id,
                                                                    "val_loss")}
    assert {k: v[0] for k, v in history.items()} == want
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    assert Observer.load(run.info.run_id).window == (40 if trained else 20)


@pytest.mark.slow
def test_a_run_killed_before_its_first_checkpoint_is_replaced(tmp_path, smoke_data):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri, "PYTHONUNBUFFERED": "1"}
    out = tmp_path / "out"
    short = "trainer.max_epochs=2"  # killed before its first epoch ends: two are plenty
    cmd = _train_cmd(tmp_path, smoke_data, out, short)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    watcher = kill_when_written(proc, out / "config.yaml")  # logged, no epoch done
    proc.wait(timeout=300)
    watcher.join()
    assert proc.returncode == -signal.SIGKILL and not (out / "checkpoints" / "last.ckpt").exists()
    rerun = cli("lbo.train", *_train_args(tmp_path, smoke_data, out, short),
                env={"MLFLOW_TRACKING_URI": uri})
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("lbo-smoke")
    finished = client.search_runs([exp.experiment_id], "attributes.status = 'FINISHED'")
    killed = [r for r in client.search_runs([exp.experiment_id], run_view_type=3)
              if r.info.run_id != finished[0].info.run_id]
    assert len(finished) == 1 and len(killed) == 1
    assert killed[0].info.lifecycle_stage == "deleted"
    assert (f"deleted the unfinished run {killed[0].info.run_id} (RUNNING) of the same "
            "config") in rerun.stdout
    assert [a.path for a in client.list_artifacts(finished[0].info.run_id, "checkpoints")] == \
        ["checkpoints/best.ckpt"]


def test_a_non_finite_estimate_is_never_valid():
    net = WindowNet("cnn", 20, "relative")
    with torch.no_grad():
        next(net.net.parameters())[0].fill_(float("nan"))
    m = np.cumsum(np.full((60, 3), 0.1), axis=0)
    est, valid = Observer.from_net(net).run(m, np.tile([5.0, 0.0], (60, 1)))
    assert np.isnan(est[19:]).all() and not valid.any()  # first 19 rows: the EKF, not valid
    assert np.isfinite(est[:19]).all()


def test_a_bad_metric_reference_stops_training_before_anything_is_written(tmp_path, smoke_data):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    res = cli("lbo.train", "experiment=smoke", "metric.reference=foo",
              f"data.root={smoke_data.parent}", f"output_dir={tmp_path / 'out'}",
              f"hydra.run.dir={tmp_path / 'h'}", env={"MLFLOW_TRACKING_URI": uri})
    assert res.returncode == 2
    assert res.stderr.strip() == ("error: metric.reference must be one of ['ekf', 'paper'], "
                                  "got 'foo'")
    assert not (tmp_path / "out").exists() and not (tmp_path / "mlflow.db").exists()


def test_datagen_removes_the_temp_files_of_a_killed_run(tmp_path):
    from lbo.sim.datasets import build, spec_from_cfg

    spec = spec_from_cfg(compose_cfg("datagen", ["data=smoke", f"data.root={tmp_path}"]))
    spec.folder.mkdir(parents=True)
    # this lbo's temps, and an older lbo's (.tmp) of the same files
    left = [spec.folder / ".train.parquet.q1w2.lbo-tmp", spec.folder / ".test.parquet.abc123.tmp",
            spec.folder / ".test_manoeuvres.png.x.tmp"]
    foreign = spec.folder / ".notes.txt.swp.tmp"  # another program's, being written there
    for p in (*left, foreign):
        p.write_bytes(b"half written")
    build(spec, progress=False)
    assert not any(p.exists() for p in left)
    assert not list(spec.folder.glob(".*.lbo-tmp"))
    assert sorted(spec.folder.glob(".*.tmp")) == [foreign]
    assert (spec.folder / "test.parquet").is_file()


@pytest.mark.parametrize("override, message", [
    ("classical=[ekf,kalman]", "classical: unknown observer 'kalman'; expected names from"),
    ("windows=[20,3]",
     "model.window must be an integer >= 4 (the CNN pools windows by 4), got 3"),
    ("models=[cnn,gru]", "models must be a list of models with a search space (cnn, "
                         "kalmannet, lstm, split_kalmannet), got ['cnn', 'gru']"),
    ("train_overrides=['metric.reference=foo']",
     "metric.reference must be one of ['ekf', 'paper'], got 'foo'"),
    ("literal=[cnn60]", "literal must be a list of <model>-N<window> (e.g. cnn-N60), "
                        "got 'cnn60'"),
    ("study=cars", "study must be paper, dynamic or all, got 'cars'"),
    ("study=dynamic", "study=dynamic trains nothing at scale smoke (its models, robust, "
                      "literal or dynamic_study are empty)"),
])
def test_reproduce_checks_every_field_before_its_first_stage(tmp_path, override, message):
    res = cli("lbo.reproduce", "scale=smoke", override, f"report_dir={tmp_path / 'report'}",
              f"optuna_storage=sqlite:///{tmp_path / 'optuna.db'}",
              f"overrides=['data.root={tmp_path / 'data'}']", f"hydra.run.dir={tmp_path / 'hydra'}",
              env={"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    assert res.returncode == 2, res.stdout[-2000:]
    assert res.stderr.strip().startswith(f"error: {message}"), res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hydra"]  # no data, report, store


@pytest.mark.parametrize("override, new", [("literal.quick=[]", "literal=[] scale=quick"),
                                           ("trials.paper=3", "trials=3 scale=paper"),
                                           ("search_overrides.quick.cnn=[]",
                                            "search_overrides.cnn=[] scale=quick")])
def test_a_setting_of_one_scale_in_its_old_spelling_is_one_line_naming_the_new(
        tmp_path, override, new):
    """Each scale's settings live in conf/scale/<scale>.yaml (a config group); the maps keyed
    by scale they replace are refused before Hydra reads them, with the new spelling."""
    from helpers import cli, one_line_error

    res = cli("lbo.reproduce", override, f"hydra.run.dir={tmp_path / 'hydra'}")
    scale = override.partition("=")[0].split(".")[1]
    assert one_line_error(res) == (f"error: {override}: each scale's settings are in "
                                   f"conf/scale/{scale}.yaml now; write {new}")
    assert not (tmp_path / "hydra").exists()
