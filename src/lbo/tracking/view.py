"""The runs table a person opens in ``mlflow ui``: a shared view lbo keeps on each of its
experiments, with the headline numbers as columns.

MLflow's UI lists an experiment's runs without their metrics: each is a column to pick by hand
among the config's hundreds of params. It also opens a *shared view* kept in an experiment tag
(``mlflow.sharedViewState.<key>``, the view's JSON) when its address carries
``?viewStateShareKey=<key>``. lbo keeps one, :data:`KEY`, on every experiment it logs to: the
runs' duration and headline metrics as columns, sorted by the first (the NRMSE at alpha 1 on a
test grid; the pooled NRMSE on a user's test logs), so that :func:`address` opens the runs side
by side. MLflow 3.17's UI reads it so (tested in headless Chromium).
"""

from __future__ import annotations

import json
from typing import Any
from urllib.parse import urlparse

KEY = "lbo"
"""The shared view's key, ``?viewStateShareKey=lbo``."""
TAG = f"mlflow.sharedViewState.{KEY}"
GRID = ("test_nrmse_alpha_1", "test_nrmse_alpha_3", "test_nrmse_alpha_6", "worst_oracle_ratio")
"""The headline metrics of a run scored on a test grid (lbo.learn.callbacks.Evaluation)."""
LOGS = ("test_nrmse", "ratio_to_ekf", "ratio_to_adaptive")
"""... and of one scored on a user's test logs (lbo.scoring.logscore.metrics)."""
UI = "http://127.0.0.1:5000"
"""Where ``make ui`` serves the UI of a SQLite store (a server's own address serves its)."""


def state(experiment: str) -> str:
    """The view's JSON for the experiment named ``experiment`` (``lbo-logs``: a user's test
    logs' metrics, else a test grid's)."""
    metrics = LOGS if experiment == "lbo-logs" else GRID
    return json.dumps({"selectedColumns": ["attributes.`Duration`",
                                           *(f"metrics.`{m}`" for m in metrics)],
                       "orderByKey": f"metrics.`{metrics[0]}`", "orderByAsc": True})


def keep(client: Any, experiment: Any) -> None:
    """Set the view on ``experiment`` (an MLflow Experiment) where it is missing or another."""
    wanted = state(experiment.name)
    if experiment.tags.get(TAG) != wanted:
        client.set_experiment_tag(experiment.experiment_id, TAG, wanted)


def addresses(uri: str) -> list[str]:
    """``<experiment>: <address>`` of each of lbo's experiments in the store at ``uri``
    (``lbo-<data>``, and ``lbo`` of a store made before each data set had its own), their view
    set first (a store made before lbo kept one); none for a store not made yet."""
    import mlflow

    from lbo.core.paths import sqlite_path

    path = sqlite_path(uri)
    if path is not None and not path.is_file():
        return []
    client = mlflow.MlflowClient(uri)
    out = []
    for exp in sorted(client.search_experiments(), key=lambda e: e.name):
        if exp.name == "lbo" or exp.name.startswith("lbo-"):
            keep(client, exp)
            out.append(f"{exp.name}: {address(uri, exp.experiment_id)}")
    return out


def address(uri: str, experiment_id: str) -> str:
    """The UI's address of the view on experiment ``experiment_id`` of the store at ``uri``."""
    base = uri.rstrip("/") if urlparse(uri).scheme in ("http", "https") else UI
    return f"{base}/#/experiments/{experiment_id}/runs?viewStateShareKey={KEY}"


if __name__ == "__main__":  # make ui: where each experiment's runs stand side by side
    import sys

    for line in addresses(sys.argv[1]):
        print(line)
