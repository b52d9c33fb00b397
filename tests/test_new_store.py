"""A new SQLite MLflow store is a copy of an empty one made once (lbo.tracking.new_store),
and behaves as a store MLflow made itself."""

from __future__ import annotations

import contextlib
import sqlite3

import pytest


def _rows(path, sql):
    with contextlib.closing(sqlite3.connect(path)) as db:
        return db.execute(sql).fetchall()


def _schema(path):
    """Each table and index with the set of its definition's lines: MLflow's migrations write
    a table's constraints in an order that differs from one process to the next."""
    return sorted((kind, name, frozenset(line.strip().rstrip(",") for line in sql.splitlines()))
                  for kind, name, sql in _rows(path, "SELECT type, name, sql FROM sqlite_master "
                                                     "WHERE name NOT LIKE 'sqlite_%'"))


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LBO_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "mlflow-stores"


def test_a_seeded_store_is_the_store_mlflow_makes(tmp_path, cache, monkeypatch):
    from mlflow import MlflowClient

    from lbo.tracking.runs import ensure_experiment

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    made = tmp_path / "a" / "mlflow.db"
    MlflowClient(f"sqlite:///{made}").create_experiment("lbo")  # MLflow's own new file
    monkeypatch.chdir(tmp_path / "b")
    seeded = tmp_path / "b" / "mlflow.db"
    client, exp = ensure_experiment(f"sqlite:///{seeded}", "lbo", None)
    assert len(list(cache.glob("empty-*.db"))) == 1
    assert _schema(seeded) == _schema(made)
    assert _rows(seeded, "SELECT * FROM alembic_version") == _rows(made,
                                                                   "SELECT * FROM alembic_version")
    # the Default experiment names the folder the store was opened from, not the cache's
    assert _rows(seeded, "SELECT experiment_id, name, artifact_location FROM experiments") == [
        (0, "Default", str(tmp_path / "b" / "mlruns" / "0")),
        (1, "lbo", str(tmp_path / "b" / "mlruns" / "1"))]
    run = client.create_run(exp)
    client.log_metric(run.info.run_id, "nrmse", 0.5)
    assert client.get_run(run.info.run_id).data.metrics == {"nrmse": 0.5}


def test_an_existing_store_is_never_replaced(tmp_path, cache):
    from lbo.tracking.new_store import seed

    path = tmp_path / "mlflow.db"
    path.write_bytes(b"not a database")
    seed(f"sqlite:///{path}")
    assert path.read_bytes() == b"not a database"
    assert not cache.exists()  # nothing made for a file that exists
    seed("http://127.0.0.1:5000")  # a server: nothing to copy
    seed(f"sqlite:///{tmp_path / 'missing' / 'mlflow.db'}")  # no folder: opening says so
    assert not (tmp_path / "missing").exists()


def test_a_damaged_empty_store_is_made_again(tmp_path, cache):
    from lbo.tracking.new_store import seed

    seed(f"sqlite:///{tmp_path / 'one.db'}")
    (empty,) = cache.glob("empty-*.db")
    empty.write_bytes(empty.read_bytes()[:5000])  # cut short
    seed(f"sqlite:///{tmp_path / 'two.db'}")
    assert _rows(empty, "PRAGMA quick_check") == [("ok",)]
    assert _schema(tmp_path / "two.db") == _schema(tmp_path / "one.db")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "one.db", "two.db"]


def test_where_no_empty_store_can_be_made_mlflow_makes_the_file(tmp_path, cache, monkeypatch):
    from mlflow import MlflowClient

    import lbo.tracking.new_store as new_store
    from lbo.tracking.runs import ensure_experiment

    def refuse(path):
        raise OSError("read-only cache")

    monkeypatch.setattr(new_store, "_make", refuse)
    path = tmp_path / "mlflow.db"
    _, exp = ensure_experiment(f"sqlite:///{path}", "lbo", None)
    assert MlflowClient(f"sqlite:///{path}").get_experiment(exp).name == "lbo"
    assert not list(cache.glob("*.db")) and not list(cache.glob(".*part"))


def test_looking_for_a_configs_runs_in_a_store_not_made_yet_finds_none_and_makes_none(tmp_path):
    """``resume=true`` and the training plan look for a config's runs before training: a
    SQLite store that does not exist holds none, and looking must not make the file (MLflow
    would build it, a second or more, before the training makes it as lbo does)."""
    from omegaconf import OmegaConf

    from lbo.learn.resume import prior_runs

    path = tmp_path / "mlflow.db"
    cfg = OmegaConf.create({"logger": {"tracking_uri": f"sqlite:///{path}",
                                       "experiment_name": "lbo-smoke"}})
    assert prior_runs(cfg, "0" * 16, keep_resumable=True) == (None, (None, None))
    assert not path.exists()
