"""A password in a store's URI never appears in anything lbo writes or prints."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from helpers.servers import PG_PASSWORD, PG_USER, free_port, mlflow_server, postgres
from lbo.core.redact import scrub, scrub_tree

# the tracking server has no authentication: the password only travels in the URI, so that
# every place lbo could copy the URI to is searched for it
MLFLOW_PASSWORD = "mlflow-planted-pw-91c2"


@pytest.mark.parametrize("text, shown", [
    ("postgresql://lbo:pw@127.0.0.1:5432/db", "postgresql://lbo:***@127.0.0.1:5432/db"),
    ("postgresql+psycopg://u:p%40ss@h/d?sslmode=require", "postgresql+psycopg://u:***@h/d?sslmode=require"),
    ("error: no server at http://alice:PW@127.0.0.1:5000 (ConnectionError)",
     "error: no server at http://alice:***@127.0.0.1:5000 (ConnectionError)"),
    ("'tune.storage=postgresql://a:b@c/d'", "'tune.storage=postgresql://a:***@c/d'"),
    ("postgresql://lbo@db.example.org/optuna", "postgresql://lbo@db.example.org/optuna"),
    ("sqlite:////tmp/x/mlflow.db", "sqlite:////tmp/x/mlflow.db"),
    ("http://127.0.0.1:5000/api", "http://127.0.0.1:5000/api"),
    ("postgresql://lbo@h:9/db?sslmode=require&password=pw", "postgresql://lbo@h:9/db?sslmode=require&password=***"),
])
def test_scrub_masks_only_the_password(text, shown):
    assert scrub(text) == shown


def test_scrub_tree_keeps_the_structure():
    tree = {"a": ["http://u:p@h", 1, None], "b": {"c": ("postgresql://u:p@h/d",)}}
    assert scrub_tree(tree) == {"a": ["http://u:***@h", 1, None],
                                "b": {"c": ("postgresql://u:***@h/d",)}}


def _with_password(url: str, password: str) -> str:
    scheme, rest = url.split("://", 1)
    return f"{scheme}://alice:{password}@{rest}"


def _files_holding(root: Path, secret: str) -> list[Path]:
    found = []
    for p in root.rglob("*"):
        if p.is_file() and secret.encode() in p.read_bytes():
            found.append(p)
    return found


def test_an_error_line_never_shows_the_password(tmp_path):
    dead = f"http://alice:{MLFLOW_PASSWORD}@127.0.0.1:{free_port()}"
    res = subprocess.run([sys.executable, "-m", "lbo.train", "experiment=smoke",
                          f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                         env={**os.environ, "MLFLOW_TRACKING_URI": dead}, timeout=300)
    assert res.returncode == 2
    assert "no MLflow tracking server answers at http://alice:***@127.0.0.1" in res.stderr
    assert MLFLOW_PASSWORD not in res.stdout + res.stderr
    assert _files_holding(tmp_path, MLFLOW_PASSWORD) == []


@pytest.mark.slow
def test_a_study_with_passwords_in_both_stores_writes_and_prints_none(tmp_path, smoke_data):
    """lbo.tune with the Optuna storage on PostgreSQL (password in tune.storage) and MLflow on
    a tracking server (password in MLFLOW_TRACKING_URI): every file the run wrote, the
    server's database and artifacts, and stdout/stderr are searched for both passwords."""
    with postgres() as pg, mlflow_server() as server:
        tracking = _with_password(server.url, MLFLOW_PASSWORD)
        storage = pg.url()
        assert f"{PG_USER}:{PG_PASSWORD}@" in storage
        run_dir = tmp_path / "run"
        res = subprocess.run(
            [sys.executable, "-m", "lbo.tune", "hparams_search=cnn", "experiment=smoke",
             f"data.root={smoke_data.parent}", "tune.n_trials=1", "trainer.max_epochs=1",
             "trainer.limit_train_batches=3", f"tune.storage={storage}",
             f"tune.handoff={tmp_path / 'tuned' / 'cnn.yaml'}", f"hydra.run.dir={run_dir}"],
            capture_output=True, text=True, timeout=600,
            env={**os.environ, "MLFLOW_TRACKING_URI": tracking, "OMP_NUM_THREADS": "1"})
        assert res.returncode == 0, res.stderr[-3000:]
        printed = res.stdout + res.stderr
        assert "***" in printed  # the storage is named, masked
        for secret in (PG_PASSWORD, MLFLOW_PASSWORD):
            assert secret not in printed
            assert _files_holding(tmp_path, secret) == []
            assert _files_holding(server.folder, secret) == []
        # the record of the run is there, only masked
        overrides = (run_dir / ".hydra" / "overrides.yaml").read_text()
        assert f"tune.storage=postgresql://{PG_USER}:***@127.0.0.1" in overrides
        assert (run_dir / ".hydra" / "config.yaml").is_file()
        assert (run_dir / ".hydra" / "hydra.yaml").is_file()
