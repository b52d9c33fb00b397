import hashlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import mlflow
import optuna
import pandas as pd
import pytest

from helpers import cli, kill_when_written

REPORT_FILES = ["rmse_alpha1.csv", "rmse_alpha6.csv", "nrmse.csv", "report.md",
                "friction_circle.png", "nrmse_cnn.png", "nrmse_lstm.png", "nrmse_all.png",
                "trajectory_alpha3.png", "nrmse_robust.png", "nrmse_dynamic.png", "dynamic.csv",
                "nrmse_protocols.png", "literal.csv", "outages.csv", "outages_end.png",
                "lateral_dynamic.csv"]


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def command(tmp_path):
    return [sys.executable, "-m", "lbo.reproduce", *arguments(tmp_path)]


def arguments(tmp_path):
    return ["scale=smoke", f"report_dir={tmp_path / 'report'}",
            f"optuna_storage=sqlite:///{tmp_path / 'optuna.db'}",
            f"overrides=['data.root={tmp_path / 'data'}']",
            "train_overrides=['trainer.limit_train_batches=4','trainer.max_epochs=1']",
            "study=all", "dynamic_study=[dynamic]",  # the car that slips too, at smoke size
            f"hydra.run.dir={tmp_path / 'hydra'}"]


@pytest.mark.slow
def test_reproduce_smoke_killed_and_resumed_without_duplicates(tmp_path):
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
           "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(command(tmp_path), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    # kill the fourth observer's run once it has finished an epoch, before it finishes
    killed_at = tmp_path / "report" / "runs" / "cnn-N80" / "checkpoints" / "last.ckpt"
    watcher = kill_when_written(proc, killed_at)
    seen = list(proc.stdout)
    proc.wait(timeout=60)
    watcher.join()
    assert proc.returncode == -signal.SIGKILL, "".join(seen[-30:])
    assert not (tmp_path / "report" / "report.md").exists()
    assert "4/11 cnn-N80" not in "".join(seen)  # killed inside the run, after its checkpoint

    # the rerun in this process: only the kill needs a process of its own
    done = cli("lbo.reproduce", *arguments(tmp_path),
               env={"MLFLOW_TRACKING_URI": env["MLFLOW_TRACKING_URI"]})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    out = done.stdout
    for i in range(1, 6):
        assert f"==> [{i}/5]" in out and f"<== [{i}/5]" in out  # a banner per stage
    assert "<== [1/5] data: done" in out
    assert "<== [2/5] tune: reused" in out
    assert out.count("reusing finished run") == 3  # cnn-N20, N40, N60 finished before the kill
    assert out.count("resuming the killed run") == 1  # cnn-N80, from its last checkpoint
    # each progress line names its job: the paper's observer, or the job and its observer
    assert "5/11 lstm-N20: reused" in out or "5/11 lstm-N20: trained" in out
    assert "9/11 robust (filternet-N100): trained" in out
    assert "10/11 literal-cnn-N20 (cnn-N20): trained" in out
    # one line per run, no run's progress bars (training or validation) between them
    said = "".join(seen) + out + done.stderr
    assert "epoch 1 of" not in said and "Validation DataLoader" not in said

    report = tmp_path / "report"
    for name in REPORT_FILES:
        assert (report / name).stat().st_size > 100, name
    t1 = pd.read_csv(report / "rmse_alpha1.csv")
    assert list(t1["variable"]) == ["x", "y", "psi"]
    assert {"ekf", "ekf_paper", "cnn", "cnn_paper", "lstm", "lstm_paper"} <= set(t1.columns)
    assert t1.loc[t1["variable"] == "x", "ekf_paper"].item() == 0.24
    nrmse = pd.read_csv(report / "nrmse.csv")
    expected = {f"{m}-N{n}" for m in ("cnn", "lstm") for n in (20, 40, 60, 80)}
    expected.add("filternet-N100")  # the robust observer, beyond the paper
    assert expected | {"ekf", "oracle", "adaptive", "ukf", "pcrb"} == set(nrmse["observer"])
    assert nrmse.groupby("observer").size().eq(7).all()  # every observer at every alpha
    ratio = nrmse.set_index(["observer", "alpha"])["ratio_to_oracle"]
    assert ratio[("oracle", 1.0)] == pytest.approx(1.0)
    assert ratio[("filternet-N100", 3.0)] == pytest.approx(
        nrmse.set_index(["observer", "alpha"]).loc[("filternet-N100", 3.0), "nrmse"]
        / nrmse.set_index(["observer", "alpha"]).loc[("oracle", 3.0), "nrmse"])
    md = (report / "report.md").read_text()
    assert "Table I" in md and "overtakes the EKF" in md and "cnn-N20" in md
    assert "Beyond the paper" in md and "crosses the EKF" in md and "filternet-N100" in md
    assert "## Where learning beats the model: `data=dynamic`" in md
    # the paper's protocol as lbo trains it (the stored noise draw), beside ours
    assert "## The paper's protocol beside ours" in md and "| literal-cnn-N20 |" in md
    literal = pd.read_csv(report / "literal.csv")
    assert set(literal["observer"]) == {"literal-cnn-N20"} and len(literal) == 7
    # its lateral states beside the EKF told the car's (its body's v_y and r)
    assert "The states no sensor gives" in md
    lateral = pd.read_csv(report / "lateral_dynamic.csv")
    assert list(dict.fromkeys(lateral["observer"])) == ["filternet-N100", "oracle_dynamic",
                                                        "kinematic", "zero"]
    assert lateral.loc[lateral["observer"] == "filternet-N100", "rmse_beta"].notna().all()
    # with beta's NEES: its variance made of the body's error on the validation set
    assert (lateral.loc[lateral["observer"] == "filternet-N100", "nees_beta"] > 0).all()
    assert "| observer | alpha | beta (deg) | v_y (m/s) | r (rad/s) | beta NEES |" in md
    dynamic = pd.read_csv(report / "dynamic.csv")  # scored on its own test set, with its oracle
    assert set(dynamic["observer"]) == {"filternet-N100", "ekf", "oracle", "adaptive",
                                        "oracle_tuned", "oracle_dynamic"}
    # through GNSS outages (scale/smoke.yaml: 3 s every 6 s): the robust observer, which
    # coasts, beside the classical filters, each with its NEES through them
    assert "## Through GNSS outages" in md and "![outages](outages_end.png)" in md
    through = pd.read_csv(report / "outages.csv")
    assert set(through["estimator"]) == {"filternet-N100", "ekf", "oracle", "adaptive", "ukf"}
    assert through.groupby("estimator").size().eq(7).all()
    assert through[["end_m", "nees"]].notna().all().all()
    stages = json.loads((report / "stages.json").read_text())
    assert list(stages) == ["data", "tune", "train", "evaluate", "report"]

    client = mlflow.MlflowClient(env["MLFLOW_TRACKING_URI"])
    # an experiment per data set: the smoke sets' runs and the report's, and the car that slips'
    exps = [client.get_experiment_by_name(f"lbo-{d}").experiment_id for d in ("smoke", "dynamic")]
    runs = client.search_runs(exps, "attributes.status = 'FINISHED'")
    def literal(r) -> bool:  # the paper's protocol: trained on the stored noise draw
        return r.data.tags["train_noise"] == "stored"

    # each run once, each under its own name (the literal protocol's, the robust and the
    # car-that-slips observers' apart from the paper protocol's)
    paper = {f"{m}-N{n}" for m in ("cnn", "lstm") for n in (20, 40, 60, 80)}
    named = {*paper, "robust-filternet-N100", "dynamic-filternet-N100", "literal-cnn-N20"}
    trained = [(r.info.run_name, r.data.tags["data"], literal(r)) for r in runs
               if "optuna_trial" not in r.data.tags and r.info.run_name in named]
    assert sorted(trained) == sorted([(n, "smoke", False) for n in paper]
                                     + [("robust-filternet-N100", "smoke", False),
                                        ("dynamic-filternet-N100", "dynamic", False),
                                        ("literal-cnn-N20", "smoke", True)])
    # every observer's folder holds one best.ckpt, the very file its MLflow run logged (the
    # report reads that artifact), beside the last epoch's: the resumed cnn-N80 finished its
    # own run in its own folder
    for r in runs:
        if r.info.run_name in expected:
            key = "dynamic" if r.data.tags["data"] == "dynamic" else "robust" \
                if r.info.run_name.startswith("filternet") else r.info.run_name
            key = f"literal-{key}" if literal(r) else key
            folder = tmp_path / "report" / "runs" / key / "checkpoints"
            assert sorted(p.name for p in folder.iterdir()) == ["best.ckpt", "last.ckpt"], key
            logged = mlflow.artifacts.download_artifacts(
                run_id=r.info.run_id, artifact_path="checkpoints/best.ckpt",
                dst_path=str(tmp_path / "dl" / key), tracking_uri=env["MLFLOW_TRACKING_URI"])
            assert _sha(Path(logged)) == _sha(folder / "best.ckpt"), key
    reports = [r for r in runs if r.data.tags.get("lbo_report") == "smoke"]
    assert len(reports) == 1
    assert {a.path for a in client.list_artifacts(reports[0].info.run_id)} >= set(REPORT_FILES)
    for model in ("cnn", "lstm"):
        study = optuna.load_study(study_name=f"{model}-smoke-N20",
                                  storage=f"sqlite:///{tmp_path / 'optuna.db'}")
        assert len(study.trials) == 2


def test_expected_steps_and_eta_arithmetic():
    from omegaconf import OmegaConf

    from lbo.learn.eta import Eta, duration, steps_per_run

    def cfg(limit):
        return OmegaConf.create({"trainer": {"max_epochs": 6, "limit_train_batches": limit}})

    assert steps_per_run(cfg(0.2), 1000) == 6 * 200      # a fraction of the epoch
    assert steps_per_run(cfg(100), 1000) == 6 * 100      # a count
    assert steps_per_run(cfg(5000), 1000) == 6 * 1000    # never more than the epoch has
    assert steps_per_run(cfg(None), 1000) == 6 * 1000
    assert [duration(s) for s in (42, 95, 7300)] == ["42 s", "1 min 35 s", "2 h 2 min"]
    eta = Eta([10.0, 20.0, 30.0])
    assert eta.skipped(0) == 50.0                        # a reused run takes nothing
    assert eta.finished(1, 40.0) == 60.0                 # twice as slow as measured: x2
    assert eta.finished(2, 60.0) == 0.0


@pytest.mark.parametrize(("each_s", "measured"), [(0.01, 1), (0.3, 1), (100.0, 4)])
def test_the_plan_stops_measuring_where_measuring_costs_about_what_training_does(
        monkeypatch, capsys, each_s, measured):
    """Timing a run takes 0.05 s here: runs of 0.01 s each (a smoke study), or of 0.3 s (the
    timing a sixth of the run: more than eta.TIMING_SHARE), are measured once and the rest
    expected to take as long; runs of 100 s are each measured."""
    import time

    from omegaconf import OmegaConf

    from lbo.learn import eta

    calls = []

    def measure(cfg):
        calls.append(cfg.seed)
        time.sleep(0.05)
        return {"steps": 4, "step_s": each_s / 8, "setup_s": 0.0, "eval_s": each_s / 2,
                "seconds": each_s * (1 + cfg.seed), "timed": 4}

    monkeypatch.setattr(eta, "measure", measure)
    monkeypatch.setattr("lbo.learn.resume.finished_run", lambda *a, **k: None)
    monkeypatch.setattr("lbo.learn.identity.config_hash", lambda cfg: "h")
    runs = [(f"run{i}", OmegaConf.create({"seed": i, "trainer": {"accelerator": "cpu"}}))
            for i in range(4)]
    plan = eta.plan(runs, scale="smoke")
    said = capsys.readouterr().out
    assert calls == list(range(measured))
    if measured == 1:
        assert plan.estimates == [each_s] * 4  # the measured one's time, each
        assert "the other 3: about 0 s each, as the 1 measured" in said
    else:
        assert plan.estimates == [100.0, 200.0, 300.0, 400.0] and "the other" not in said
    assert "expected: about" in said


def test_a_measured_step_gives_the_runs_expected_time(tmp_path, smoke_data):
    from helpers import train_cfg
    from lbo.learn.eta import measure

    m = measure(train_cfg(tmp_path, smoke_data, "trainer.max_epochs=2",
                          "trainer.limit_train_batches=5"), steps=4)
    assert m["steps"] == 10 and 0 < m["step_s"] < 5
    # and the forward passes beside the steps: each epoch's validation, the test set's scoring
    assert 0 < m["eval_s"] < 60
    assert m["seconds"] == pytest.approx(m["setup_s"] + 10 * m["step_s"] + m["eval_s"])
    assert m["timed"] == 3 + 4  # warm-up and the steps asked for
    # a run of 4 steps is timed on 4 steps, not the 11 (3 + 8) a longer one is
    short = measure(train_cfg(tmp_path, smoke_data, "trainer.max_epochs=1",
                              "trainer.limit_train_batches=4"))
    assert (short["steps"], short["timed"]) == (4, 4) and 0 < short["step_s"] < 5
