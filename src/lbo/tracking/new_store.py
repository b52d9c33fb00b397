"""A new SQLite MLflow store, copied from an empty one made once per MLflow version.

MLflow builds a new SQLite store's tables by replaying its schema migrations one by one: 3 s
for every new file on a 2-core machine, in every project, test and temporary folder. lbo makes
an empty store once per MLflow version in its cache folder and copies it (milliseconds). The
copy holds MLflow's tables and nothing else: MLflow adds its Default experiment, whose
artifact folder depends on where the store is opened, when it first opens the copy, as it does
in a file it made itself.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import uuid
from pathlib import Path

from lbo.core.paths import cache_dir, sqlite_path


def seed(uri: str) -> None:
    """Copy the empty store to the SQLite file behind ``uri`` if that file does not exist yet.

    Does nothing for a server, a database other than SQLite, an existing file or a missing
    folder (opening the store says what is wrong). Where the empty store cannot be made or
    read, MLflow builds the file itself, as it would without lbo. Callers hold
    :func:`lbo.tracking.runs.creation_lock`, so that two jobs never seed one file together.
    """
    path = sqlite_path(uri)
    if path is None or path.exists() or not path.parent.is_dir():
        return
    try:
        empty = _empty_store()
    except Exception:  # noqa: BLE001 - an optimisation only: MLflow makes the file instead
        return
    part = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        shutil.copyfile(empty, part)
        os.replace(part, path)  # whole or not at all: a reader never sees half a copy
    except OSError:
        pass  # the folder is read-only or full: opening the store says so
    finally:
        part.unlink(missing_ok=True)


def _empty_store() -> Path:
    """The cache's empty store for the installed MLflow, made under a lock if missing or
    damaged."""
    import mlflow
    from filelock import FileLock

    folder = cache_dir() / "mlflow-stores"
    folder.mkdir(parents=True, exist_ok=True)
    empty = folder / f"empty-{mlflow.__version__}.db"
    if _intact(empty):
        return empty
    with FileLock(str(empty) + ".lock", timeout=600):
        if _intact(empty):
            return empty
        # a name never used before: MLflow keeps each store it opened, by its URI, for the
        # life of the process, and would not build the tables in a second file of one name
        part = folder / f".{empty.name}.{uuid.uuid4().hex}.part"
        try:
            _make(part)
            os.replace(part, empty)
        finally:
            part.unlink(missing_ok=True)
    return empty


def _make(path: Path) -> None:
    """Have MLflow build its tables in a new file at ``path``, then take out the Default
    experiment it adds, which names a folder of this process."""
    from mlflow import MlflowClient

    client = MlflowClient(f"sqlite:///{path}")
    client.search_experiments()  # builds the tables
    store = client._tracking_client.store
    with contextlib.suppress(AttributeError):
        store.engine.dispose()  # no connection kept to a file about to be renamed
    with contextlib.closing(sqlite3.connect(path)) as db:
        db.execute("DELETE FROM experiments")
        db.commit()


def _intact(path: Path) -> bool:
    """True if ``path`` is a SQLite file with MLflow's tables and no experiment in them."""
    if not path.is_file():
        return False
    try:
        with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
            if db.execute("PRAGMA quick_check").fetchone()[0] != "ok":
                return False
            version = db.execute("SELECT version_num FROM alembic_version").fetchall()
            experiments = db.execute("SELECT COUNT(*) FROM experiments").fetchone()[0]
    except sqlite3.Error:
        return False
    return len(version) == 1 and experiments == 0
