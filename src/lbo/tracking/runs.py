"""The stores that runs share: an MLflow tracking server or SQLite file, and Hydra launchers.

Every entry point checks these before any work starts, so that a wrong address, a missing
plugin or a store that concurrent jobs would lock stops with one line, and no run is left
RUNNING.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from lbo.core.errors import LboError
from lbo.core.paths import sqlite_path
from lbo.core.redact import scrub
from lbo.tracking import view

#: Seconds a probe of a tracking server waits before saying it does not answer.
PROBE_TIMEOUT = 5.0
#: Seconds a SQLite writer waits for another process's write before failing.
SQLITE_BUSY_S = 120


def is_server(uri: str) -> bool:
    return urlparse(uri).scheme in ("http", "https")


def check_server(uri: str, field: str = "logger.tracking_uri") -> None:
    """Raise one line unless the MLflow tracking server at ``uri`` answers its health check.

    Without this, MLflow's client retries a dead address with backoff for minutes and then
    prints a page of urllib3 errors.
    """
    if not is_server(uri):
        return
    import requests

    shown = scrub(uri)

    health = uri.rstrip("/") + "/health"
    try:
        reply = requests.get(health, timeout=PROBE_TIMEOUT)
    except requests.RequestException as e:
        reason = type(e).__name__
        raise LboError(f"{field}: no MLflow tracking server answers at {shown} ({reason}); "
                       "start one (make mlflow-server) or unset MLFLOW_TRACKING_URI") from e
    if reply.status_code != 200:
        raise LboError(f"{field}: {shown} is not an MLflow tracking server (GET /health gave "
                       f"HTTP {reply.status_code})")


#: Tracking-store schemes MLflow reads (a database may name its driver: postgresql+psycopg).
STORE_SCHEMES = ("sqlite", "postgresql", "mysql", "mssql", "http", "https", "databricks")


def store_field(uri: str, field: str = "logger.tracking_uri") -> str:
    """The name to blame for a bad store: MLFLOW_TRACKING_URI when the store came from it."""
    import os

    return "MLFLOW_TRACKING_URI" if os.environ.get("MLFLOW_TRACKING_URI") == uri else field


def check_store(uri: str, field: str = "logger.tracking_uri") -> None:
    """Raise one line unless the MLflow tracking store ``uri`` can be used: a scheme MLflow
    knows, a server that answers, a SQLite file whose folder exists and can be written and
    that reads as a database, a database that accepts a connection. Passwords never appear
    in the line."""
    from urllib.parse import urlparse

    field = store_field(uri, field)
    shown = scrub(uri)
    scheme = urlparse(uri).scheme.split("+")[0]
    if scheme not in STORE_SCHEMES:
        raise LboError(f"{field}: {shown!r} is not a tracking store lbo can use (give "
                       "sqlite:///<file>, http(s)://<host>:<port> of an MLflow server, or "
                       "postgresql://<user>@<host>/<database>)")
    if is_server(uri):
        check_server(uri, field)
        return
    path = sqlite_path(uri)
    if scheme == "sqlite":
        if path is None:
            raise LboError(f"{field}: {shown!r} names no SQLite file (give sqlite:///<file>)")
        _check_writable(path, field)
        _check_intact(path, field)
    elif scheme in ("postgresql", "mysql", "mssql"):
        _check_database(uri, field)


def _check_writable(path, field: str) -> None:
    import os

    folder = path.parent
    if not folder.is_dir():
        raise LboError(f"{field}: the folder of the SQLite store {path} does not exist")
    target = path if path.exists() else folder
    if not os.access(target, os.W_OK):
        what = "file" if target == path else "folder"
        raise LboError(f"{field}: cannot write the SQLite store {path} (its {what} is "
                       "read-only); point MLFLOW_TRACKING_URI at a folder you can write")


def _check_intact(path: Path, field: str) -> None:
    """Refuse a SQLite store whose file is not a database (overwritten, truncated): MLflow's
    SQLAlchemy store would fail on it with pages of SQL, after the run had started."""
    from lbo.core.cli import damaged_store_message, sqlite_damage

    reason = sqlite_damage(path)
    if reason is not None:
        raise LboError(damaged_store_message(field, path, reason))


def _check_database(uri: str, field: str) -> None:
    """Connect once, with a short timeout, to the database behind ``uri``."""
    from sqlalchemy import create_engine
    from sqlalchemy.pool import NullPool

    shown = scrub(uri)
    args = {"connect_timeout": int(PROBE_TIMEOUT)} if uri.startswith("postgresql") else {}
    try:
        engine = create_engine(uri, poolclass=NullPool, connect_args=args)
        try:
            with engine.connect():
                pass
        finally:
            engine.dispose()
    except ImportError as e:
        raise LboError(f"{field}: cannot open {shown}: its database driver is not installed "
                       f"({e})") from None
    except Exception as e:  # sqlalchemy.exc.OperationalError, ArgumentError
        reason = " ".join((str(getattr(e, "orig", None) or e).strip().splitlines() or [""])[:1])
        raise LboError(f"{field}: cannot open the tracking store {shown} "
                       f"({type(e).__name__}: {scrub(reason)})") from None


@contextlib.contextmanager
def creation_lock(uri: str) -> Iterator[None]:
    """Hold a lock, per machine, on the SQLite database behind ``uri`` (no-op for a server).

    Neither optuna nor MLflow survives two processes creating the same new SQLite file at once
    (both migrate its tables), and jobs started together would do just that. The lock file
    sits beside the database (``<name>.lock``), so it goes where the database goes.
    """
    from filelock import FileLock

    path = sqlite_path(uri)
    if path is None or not path.parent.is_dir():  # no folder: opening the store will say so
        yield
        return
    with FileLock(path.with_name(path.name + ".lock"), timeout=600):
        yield


def use_wal(uri: str) -> None:
    """Switch the SQLite file behind ``uri`` (if any, and if it exists) to write-ahead logging.

    In WAL mode readers never block the writer, so parallel jobs (``hydra/launcher=joblib``)
    that log metrics while others read do not fail with "database is locked"; writers still
    take turns, and MLflow's connections wait for each other (SQLite's busy timeout). The
    mode is stored in the file, so one call covers every later process.
    """
    path = sqlite_path(uri)
    if path is None or not path.is_file():
        return
    with contextlib.closing(sqlite3.connect(path, timeout=SQLITE_BUSY_S)) as db:
        if db.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
            db.execute("PRAGMA journal_mode=WAL")


def dataset_input(name: str, digest: str, source: str | Path, context: str = "training") -> Any:
    """The data set a run reads, as an MLflow dataset input (``MlflowClient.log_inputs``):
    its name, lbo's data hash as its digest (MLflow keeps 36 characters) and its folder, so
    that MLflow's UI lists it with the run and groups the runs that read the same data."""
    import json

    from mlflow.entities import Dataset, DatasetInput, InputTag

    return DatasetInput(Dataset(name=name, digest=digest[:36], source_type="local",
                                source=json.dumps({"uri": str(source)})),
                        tags=[InputTag("mlflow.data.context", context)])


DUPLICATE_KEY = ("UNIQUE constraint failed", "duplicate key value violates unique constraint",
                 "Duplicate entry")
"""How a store's database refuses a second record under a unique key (SQLite, PostgreSQL,
MySQL), in the error MLflow passes on."""


def log_input(client: Any, run_id: str | None, dataset: Any, tries: int = 3) -> None:
    """Log a dataset input (:func:`dataset_input`) to run ``run_id`` through MLflow client
    ``client``.

    MLflow's store records each data set once per experiment: it looks the record up, and
    inserts it when missing. Runs started at the same moment on the same data (the jobs of
    a SLURM array, against a tracking server) both find it missing, and the second insert
    fails on the database's unique key (measured: one of two jobs failed so). The record
    exists by then: the input is logged again, up to ``tries`` times in all."""
    import time

    from mlflow.exceptions import MlflowException

    for attempt in range(1, tries + 1):
        try:
            client.log_inputs(run_id, datasets=[dataset])
            return
        except MlflowException as e:
            if attempt == tries or not any(k in str(e) for k in DUPLICATE_KEY):
                raise
            time.sleep(0.2 * attempt)


KIND_TAG, KIND = "mlflow.experimentKind", "custom_model_development"
"""The experiment tag that makes MLflow 3's UI open an experiment in its model-training view
(runs, metrics, charts), not in its GenAI one (traces, prompts), which it would guess."""


def ensure_experiment(uri: str, name: str, artifact_location: str | None):
    """An MLflow client on the store at ``uri`` and the id of experiment ``name``, created if
    missing, the store in WAL mode if it is SQLite. Returns ``(client, experiment_id)``.
    Callers have checked a server with :func:`check_server` first.

    Jobs started together would each create the store's tables, or the experiment, and all but
    one would fail: the first one does it under :func:`creation_lock`, and an experiment that
    another machine created a moment ago is looked up again.
    """
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    from lbo.tracking.new_store import seed

    with creation_lock(uri):
        seed(uri)  # a new SQLite file from an empty store, not MLflow's 3 s of migrations
        client = MlflowClient(uri)
        use_wal(uri)
        exp = client.get_experiment_by_name(name)
        if exp is not None:
            if exp.tags.get(KIND_TAG) != KIND:  # one lbo made before it set the kind
                client.set_experiment_tag(exp.experiment_id, KIND_TAG, KIND)
            view.keep(client, exp)  # ... or before it kept its runs table's view
            return client, exp.experiment_id
        try:
            return client, client.create_experiment(name, artifact_location=artifact_location,
                                                    tags={KIND_TAG: KIND,
                                                          view.TAG: view.state(name)})
        except MlflowException:
            exp = client.get_experiment_by_name(name)
            if exp is None:
                raise
            return client, exp.experiment_id


def logger_experiment(logger: Any):
    """:func:`ensure_experiment` for a training config's ``logger`` group (its
    ``tracking_uri``, ``experiment_name`` and ``artifact_location``, null for the default):
    ``(client, experiment_id)``."""
    return ensure_experiment(logger.tracking_uri, logger.experiment_name,
                             logger.get("artifact_location"))


def run_artifact(run: dict[str, Any], path: str, tracking_uri: str) -> Path:
    """A file logged by a training run (``run["run_id"]``), fetched from its MLflow
    artifacts."""
    import mlflow

    with no_progress_bar():  # a bar per small file, between a command's own lines
        return Path(mlflow.artifacts.download_artifacts(run_id=run["run_id"],
                                                        artifact_path=path,
                                                        tracking_uri=tracking_uri))


PROGRESS_BAR = "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"


@contextlib.contextmanager
def no_progress_bar() -> Iterator[None]:
    """MLflow's download bars off for the ``with`` block (a checkpoint of a few MB comes in a
    blink, and the bars would sit between a command's own lines), unless the user set
    :data:`PROGRESS_BAR`."""
    if PROGRESS_BAR in os.environ:
        yield
        return
    os.environ[PROGRESS_BAR] = "false"
    try:
        yield
    finally:
        os.environ.pop(PROGRESS_BAR, None)
