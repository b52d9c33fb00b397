"""The runs table a person opens in ``mlflow ui`` (lbo.tracking.view), as MLflow's own UI renders
it in headless Chromium, from a real ``mlflow server`` on a store a training made."""

from __future__ import annotations

import json
import re
import shutil
import sqlite3
import subprocess

import mlflow
import pytest

from helpers import store_client
from helpers.servers import mlflow_server
from lbo.core.paths import sqlite_path
from lbo.tracking import view

CHROMIUM = shutil.which("chromium-headless-shell") or shutil.which("chromium")


def rendered(url: str) -> str:
    """The words of the page at ``url`` once its scripts have run (tags and styles cut)."""
    res = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                          "--window-size=1920,1080", "--virtual-time-budget=20000",
                          "--dump-dom", url], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    text = re.sub(r"<style[^<]*</style>", " ", res.stdout)
    return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", text))


def test_the_view_names_its_columns_as_mlflows_table_keys_them():
    grid = json.loads(view.state("lbo-smoke"))
    assert grid["selectedColumns"] == ["attributes.`Duration`", "metrics.`test_nrmse_alpha_1`",
                                       "metrics.`test_nrmse_alpha_3`",
                                       "metrics.`test_nrmse_alpha_6`",
                                       "metrics.`worst_oracle_ratio`"]
    assert (grid["orderByKey"], grid["orderByAsc"]) == ("metrics.`test_nrmse_alpha_1`", True)
    assert json.loads(view.state("lbo-logs"))["orderByKey"] == "metrics.`test_nrmse`"
    assert view.address("sqlite:////x/mlflow.db", "3") == \
        "http://127.0.0.1:5000/#/experiments/3/runs?viewStateShareKey=lbo"
    assert view.address("http://10.0.0.2:5000/", "7") == \
        "http://10.0.0.2:5000/#/experiments/7/runs?viewStateShareKey=lbo"


@pytest.mark.slow  # a real MLflow server and two pages rendered: about 20 s
def test_the_runs_of_a_fresh_store_show_their_headline_metrics_at_lbos_address(tmp_path,
                                                                              smoke_cnn):
    assert CHROMIUM, ("headless Chromium is missing: apt-get install chromium-headless-shell "
                      "(.ci/run installs it)")
    store = tmp_path / "mlflow.db"  # a copy: the fixture's store is read by other tests
    with sqlite3.connect(sqlite_path(smoke_cnn["uri"])) as src, sqlite3.connect(store) as dst:
        src.backup(dst)
    client = mlflow.MlflowClient(f"sqlite:///{store}")
    exp = client.get_experiment_by_name("lbo-smoke")
    assert exp.tags[view.TAG] == view.state("lbo-smoke")  # kept as the training made the store
    run = client.get_run(smoke_cnn["run_id"])
    with mlflow_server(f"sqlite:///{store}") as server:
        shown = rendered(view.address(server.url, exp.experiment_id))
        plain = rendered(f"{server.url}/#/experiments/{exp.experiment_id}/runs")
    for metric in view.GRID:  # each headline metric a column of the runs table, with its value
        assert f" {metric} " in shown, shown[-3000:]
    assert "cnn-N20" in shown and repr(run.data.metrics["test_nrmse_alpha_1"]) in shown
    # MLflow's own table, without the view: the metrics hidden among hundreds of columns
    assert " test_nrmse_alpha_1 " not in plain and "Show more columns" in plain


def test_make_ui_lists_the_view_of_each_of_lbos_experiments(tmp_path):
    """``python -m lbo.tracking.view <uri>`` (make ui): an address per experiment of lbo's,
    its view set first where a store made before lacks it; nothing for a store not made."""
    from helpers import cli

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert view.addresses(uri) == [] and not (tmp_path / "mlflow.db").exists()
    client = store_client(uri)
    ids = {name: client.create_experiment(name) for name in ("lbo", "lbo-smoke", "someone's")}
    res = cli("lbo.tracking.view", uri, process=True)  # a module run as make ui runs it
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.splitlines() == [f"{n}: {view.address(uri, ids[n])}"
                                       for n in ("lbo", "lbo-smoke")]
    assert client.get_experiment(ids["lbo-smoke"]).tags[view.TAG] == view.state("lbo-smoke")
    assert view.TAG not in client.get_experiment(ids["someone's"]).tags
