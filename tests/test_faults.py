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

from conftest import compose_cfg, kill_when_written
from lbo.network import ObserverNet
from lbo.observer import Observer


@pytest.mark.slow
def test_a_run_killed_after_its_checkpoint_does_not_poison_the_rerun(tmp_path, smoke_data,
                                                                     monkeypatch):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri, "PYTHONUNBUFFERED": "1"}
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "lbo.train", "experiment=smoke", "resume=true",
           f"data.root={smoke_data.parent}", f"output_dir={out}", "trainer.max_epochs=6",
           f"hydra.run.dir={tmp_path / 'hydra'}"]
    ckpt = out / "checkpoints" / "best.ckpt"
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    watcher = kill_when_written(proc, ckpt)
    proc.wait(timeout=300)
    watcher.join()
    assert proc.returncode == -signal.SIGKILL and ckpt.exists()

    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert "removed 1 stale checkpoint(s) of an earlier run" in rerun.stdout
    assert sorted(p.name for p in ckpt.parent.iterdir()) == ["best.ckpt"]
    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("lbo")
    finished = client.search_runs([exp.experiment_id], "attributes.status = 'FINISHED'")
    assert len(finished) == 1
    run_id = finished[0].info.run_id
    assert [a.path for a in client.list_artifacts(run_id, "checkpoints")] == \
        ["checkpoints/best.ckpt"]
    killed = [r for r in client.search_runs([exp.experiment_id], run_view_type=3)
              if r.info.run_id != run_id]
    assert len(killed) == 1 and killed[0].info.lifecycle_stage == "deleted"
    assert (f"deleted the unfinished run {killed[0].info.run_id} (RUNNING) of the same "
            "config") in rerun.stdout
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    assert Observer.load(run_id).window == 20


def test_a_non_finite_estimate_is_never_valid():
    net = ObserverNet("cnn", 20, "relative")
    with torch.no_grad():
        next(net.net.parameters())[0].fill_(float("nan"))
    m = np.cumsum(np.full((60, 3), 0.1), axis=0)
    est, valid = Observer.from_net(net).run(m, np.tile([5.0, 0.0], (60, 1)))
    assert np.isnan(est[19:]).all() and not valid.any()  # first 19 rows: the EKF, not valid
    assert np.isfinite(est[:19]).all()


def test_a_bad_metric_reference_stops_training_before_anything_is_written(tmp_path, smoke_data):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    res = subprocess.run([sys.executable, "-m", "lbo.train", "experiment=smoke",
                          "metric.reference=foo", f"data.root={smoke_data.parent}",
                          f"output_dir={tmp_path / 'out'}", f"hydra.run.dir={tmp_path / 'h'}"],
                         env={**os.environ, "MLFLOW_TRACKING_URI": uri}, capture_output=True,
                         text=True)
    assert res.returncode == 2
    assert res.stderr.strip() == ("error: metric.reference must be one of ['ekf', 'paper'], "
                                  "got 'foo'")
    assert not (tmp_path / "out").exists() and not (tmp_path / "mlflow.db").exists()


def test_datagen_removes_the_temp_files_of_a_killed_run(tmp_path):
    from lbo.datagen.build import build, spec_from_cfg

    spec = spec_from_cfg(compose_cfg("datagen", ["data=smoke", f"data.root={tmp_path}"]))
    spec.folder.mkdir(parents=True)
    left = [spec.folder / ".test.parquet.abc123.tmp", spec.folder / ".test_manoeuvres.png.x.tmp"]
    for p in left:
        p.write_bytes(b"half written")
    build(spec, progress=False)
    assert not any(p.exists() for p in left)
    assert not list(spec.folder.glob(".*.tmp"))
    assert (spec.folder / "test.parquet").is_file()


@pytest.mark.parametrize("override, message", [
    ("classical=[ekf,kalman]", "classical: unknown observer 'kalman'; expected names from"),
    ("windows=[20,3]", "window must be an integer >= 4 (the CNN pools windows by 4), got 3"),
    ("models=[cnn,gru]", "models must be a list of models with a search space (cnn, lstm), "
                         "got ['cnn', 'gru']"),
    ("train_overrides=['metric.reference=foo']",
     "metric.reference must be one of ['ekf', 'paper'], got 'foo'"),
])
def test_reproduce_checks_every_field_before_its_first_stage(tmp_path, override, message):
    res = subprocess.run([sys.executable, "-m", "lbo.reproduce", "scale=smoke", override,
                          f"report_dir={tmp_path / 'report'}",
                          f"optuna_storage=sqlite:///{tmp_path / 'optuna.db'}",
                          f"overrides=['data.root={tmp_path / 'data'}']",
                          f"hydra.run.dir={tmp_path / 'hydra'}"],
                         env={**os.environ, "MLFLOW_TRACKING_URI":
                              f"sqlite:///{tmp_path / 'mlflow.db'}"},
                         capture_output=True, text=True)
    assert res.returncode == 2, res.stdout[-2000:]
    assert res.stderr.strip().startswith(f"error: {message}"), res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hydra"]  # no data, report, store
