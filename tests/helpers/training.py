"""Training runs at smoke size for the tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from helpers.config import compose_cfg


def train_in_own_store(tmp: Path, smoke_data: Path, *overrides: str):
    """Train at smoke size into ``tmp / 'out'``, logged to an MLflow store of its own (no ONNX
    graphs kept for ``lbo.observe``, unless ``keep_onnx=true`` is among the overrides).

    Returns ``(cfg, metrics, tracking_uri)``; ``overrides`` choose the experiment and sizes.
    """
    from lbo.train import train

    uri = f"sqlite:///{tmp / 'mlflow.db'}"
    cfg = compose_cfg("train", ["keep_onnx=false", *overrides, f"data.root={smoke_data.parent}",
                                f"output_dir={tmp / 'out'}"])
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        return cfg, train(cfg), uri


def _evaluation_subclass():
    from lbo.learn.callbacks import Evaluation

    class RenamedEvaluation(Evaluation):
        """A user's evaluation callback under a name of its own: tuning must drop it too."""

    return RenamedEvaluation


def __getattr__(name: str):
    # built on first use: importing this module must not import Lightning
    if name == "RenamedEvaluation":
        return _evaluation_subclass()
    raise AttributeError(name)


def store_client(uri: str):
    """An MLflow client on the store at ``uri``; a SQLite file that does not exist yet is
    first copied from lbo's empty store, as lbo's commands make theirs (MLflow builds a new
    file by replaying its migrations: about a second each, 38 times over the suite)."""
    from mlflow import MlflowClient

    from lbo.tracking.new_store import seed

    seed(uri)
    return MlflowClient(uri)
