"""A trained observer as an MLflow model (lbo.serve.serving): every training run logs one; it loads
with mlflow.pyfunc in a fresh process and serves over HTTP with `mlflow models serve`, giving
the estimates lbo.Observer gives."""

import json
import os
import subprocess
import sys

import mlflow
import numpy as np
import pandas as pd
import pytest
import requests

from helpers import store_client
from helpers.servers import model_server
from lbo.core.errors import LboError
from lbo.export import register
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer
from lbo.serve.serving import estimates, log_model
from lbo.sim.columns import RECEIVER, SERVED, WINDOW

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]


@pytest.fixture(scope="module")
def robust(robust_smoke):
    return robust_smoke


@pytest.fixture(scope="module")
def log(manoeuvre):
    frame = manoeuvre[list(WINDOW)].reset_index(drop=True).iloc[:300].copy()
    frame.loc[frame.index % 5 != 0, ["x_m", "y_m", "psi_m"]] = np.nan  # fixes at 10 Hz
    return frame


def _single_antenna(manoeuvre, log):
    """``log`` as a single antenna gives it: no heading, each fix with its reported accuracy
    and a GNSS velocity (the truth's, 0.1 m/s sigma)."""
    frame = log.copy()
    truth = manoeuvre.reset_index(drop=True).iloc[:len(frame)]
    fix = frame["x_m"].notna()
    frame["psi_m"] = np.nan
    frame["sx_m"] = frame["sy_m"] = np.where(fix, 0.5, np.nan)
    frame["ve_m"] = np.where(fix, truth["V"] * np.cos(truth["psi"]), np.nan)
    frame["vn_m"] = np.where(fix, truth["V"] * np.sin(truth["psi"]), np.nan)
    frame["sv_m"] = np.where(fix, 0.1, np.nan)
    return frame


def _env(uri: str) -> dict[str, str]:
    return {**os.environ, "MLFLOW_TRACKING_URI": uri, "OMP_NUM_THREADS": "1"}


def _expected(robust, frame: pd.DataFrame) -> pd.DataFrame:
    os.environ["MLFLOW_TRACKING_URI"] = robust["uri"]
    try:
        return estimates(Observer.load(robust["run_id"]), frame)
    finally:
        del os.environ["MLFLOW_TRACKING_URI"]


def test_every_training_run_logs_a_model_that_pyfunc_loads_in_a_fresh_process(robust, log,
                                                                              tmp_path):
    client = mlflow.MlflowClient(robust["uri"])
    assert {"model", "checkpoints"} <= {a.path for a in client.list_artifacts(robust["run_id"])}
    run = client.get_run(robust["run_id"]).info
    assert run.status == "FINISHED"
    # and as a logged model of its run, which MLflow 3's Models tab lists
    (model,) = client.search_logged_models([run.experiment_id],
                                           filter_string=f"source_run_id = '{run.run_id}'")
    assert (model.name, model.status.to_proto(), model.model_type) == (
        run.run_name, 2, "lbo observer")  # 2: READY
    assert {a.path for a in client.list_logged_model_artifacts(model.model_id)} >= {
        "MLmodel", "artifacts"}
    log.to_parquet(tmp_path / "log.parquet")
    script = ("import mlflow, pandas as pd, sys\n"
              f"model = mlflow.pyfunc.load_model('runs:/{robust['run_id']}/model')\n"
              f"out = model.predict(pd.read_parquet(r'{tmp_path / 'log.parquet'}'))\n"
              f"out.to_parquet(r'{tmp_path / 'out.parquet'}')\n")
    res = subprocess.run([sys.executable, "-c", script], env=_env(robust["uri"]),
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    got = pd.read_parquet(tmp_path / "out.parquet")
    want = _expected(robust, log)
    assert list(got.columns) == list(SERVED) and len(got) == len(log)
    pd.testing.assert_frame_equal(got, want, atol=1e-9)
    # the robust observer knows how sure it is: a covariance on every valid row
    assert got["valid"].all() and (got[["var_x", "var_y", "var_psi"]] > 0).all(axis=None)


def test_logging_the_model_prints_no_download_bars(robust, tmp_path, capfd):
    """Training ends with its result: MLflow's bars from saving the model would follow it."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = store_client(uri)
    run = client.create_run(client.create_experiment(
        "bars", artifact_location=(tmp_path / "artifacts").as_uri()))
    capfd.readouterr()
    log_model(uri, run.info.run_id, robust["out"]["checkpoint"])
    said = capfd.readouterr()
    assert "Downloading artifacts" not in said.out + said.err
    assert "model" in {a.path for a in client.list_artifacts(run.info.run_id)}


def test_mlflow_models_serve_answers_a_posted_window(robust, log, manoeuvre):
    window = log.iloc[:40]  # one window of the observer's N, its estimate the last row's
    antenna = _single_antenna(manoeuvre, log).iloc[:60]  # and a receiver's rows
    body, body_antenna = ({"dataframe_split": json.loads(f.to_json(orient="split", index=False))}
                          for f in (window, antenna))
    with model_server(f"runs:/{robust['run_id']}/model", _env(robust["uri"])) as url:
        res = requests.post(f"{url}/invocations", json=body, timeout=60)
        res_antenna = requests.post(f"{url}/invocations", json=body_antenna, timeout=60)
        bad = requests.post(f"{url}/invocations", timeout=60,
                            json={"dataframe_split": {"columns": ["x_m"], "data": [[1.0]]}})
    for response, frame in ((res, window), (res_antenna, antenna)):
        assert response.status_code == 200, response.text
        got, want = pd.DataFrame(response.json()["predictions"]), _expected(robust, frame)
        np.testing.assert_allclose(got[["x", "y", "psi"]].to_numpy(dtype=float),
                                   want[["x", "y", "psi"]].to_numpy(), atol=1e-9)
        assert got["valid"].tolist() == want["valid"].tolist()
    # no heading in the fixes: the course over ground of the velocity columns gives it
    assert want["valid"].all()
    assert not _expected(robust, antenna.drop(columns=["ve_m", "vn_m", "sv_m"]))["valid"].any()
    # the model's signature: MLflow refuses a frame without the log's columns, naming them
    assert bad.status_code == 400 and "missing inputs" in bad.text.lower() and "delta" in bad.text


def test_the_registry_registers_the_model(robust, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", robust["uri"])
    uri = register(robust["run_id"], "lbo-robust", robust["uri"])
    assert uri == "models:/lbo-robust/1"
    assert Observer.load(uri).name == "filternet-N40"
    # a training in this process (Lightning's MLFlowLogger) sets MLflow's process-wide tracking
    # URI, which outranks the environment: name the store for MLflow's own loader
    previous = mlflow.get_tracking_uri()
    mlflow.set_tracking_uri(robust["uri"])
    try:
        model = mlflow.pyfunc.load_model(uri)  # the pyfunc model, not a folder of checkpoints
    finally:
        mlflow.set_tracking_uri(previous)
    assert list(model.metadata.get_input_schema().input_names()) == [*WINDOW, "log",
                                                                      *RECEIVER]


def test_a_log_without_its_columns_is_one_line(manoeuvre, log):
    with pytest.raises(LboError, match="model input: missing columns V, delta"):
        estimates(Observer.load("ekf"), pd.DataFrame({"x_m": [0.0], "y_m": [0.0],
                                                      "psi_m": [0.0]}))
    antenna = _single_antenna(manoeuvre, log)
    with pytest.raises(LboError, match=r"^receiver: cnn-N20 does not take a receiver's "):
        estimates(Observer.from_net(WindowNet("cnn", 20, "relative")), antenna)
    # columns a client sends empty are no receiver: a window net takes the frame
    full = manoeuvre[list(WINDOW)].reset_index(drop=True).iloc[:40]
    empty = full.assign(**{c: np.nan for c in RECEIVER})
    assert estimates(Observer.from_net(WindowNet("cnn", 20, "relative")), empty)[
        "valid"].iloc[-1]
