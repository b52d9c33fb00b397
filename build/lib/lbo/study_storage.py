"""Where an ``lbo.tune`` study lives: its database, opened with one-line errors and no
password in any line, and the lock under which workers claim trials."""

from __future__ import annotations

import hashlib
import warnings
from typing import Any

import optuna
from optuna.trial import TrialState

from lbo.errors import LboError
from lbo.paths import sqlite_path
from lbo.tracking import creation_lock

#: Trials that count towards ``tune.n_trials``; failed ones (crashes, killed processes) do not.
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
#: How to install the database drivers that SQLAlchemy asks for.
DRIVERS = {"psycopg": ' (pip install "psycopg[binary]")',
           "psycopg2": " (pip install psycopg2-binary)", "pymysql": " (pip install pymysql)",
           "MySQLdb": " (pip install mysqlclient)"}


def redact(url: str) -> str:
    """The storage URL as it may be printed and logged: without its password."""
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception as e:  # sqlalchemy.exc.ArgumentError
        raise LboError(f"tune.storage: {url!r} is not a database URL "
                       f"(sqlite:///path/optuna.db or postgresql://user:pass@host/db)") from e


def open_storage(url: str, heartbeat_interval: int,
                 grace_period: int) -> optuna.storages.RDBStorage:
    """Connect to (and if new, initialise) the study database; one line if it cannot.

    A trial whose process stops sending heartbeats for ``grace_period`` s (killed, preempted)
    is marked failed and queued once more with the same parameters.
    """
    from sqlalchemy.engine import make_url

    shown = redact(url)
    backend = make_url(url).get_backend_name()
    engine_kwargs: dict[str, Any] = {}
    if backend == "sqlite":
        # workers on one SQLite file wait for each other's writes instead of failing at once
        engine_kwargs = {"connect_args": {"timeout": 60}}
    elif backend == "postgresql":
        engine_kwargs = {"connect_args": {"connect_timeout": 10}, "pool_pre_ping": True}
    try:
        with creation_lock(url), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # heartbeats are marked experimental
            return optuna.storages.RDBStorage(
                url, engine_kwargs=engine_kwargs, heartbeat_interval=heartbeat_interval,
                grace_period=grace_period,
                heartbeat_stale_trial_callback=optuna.storages.RetryFailedTrialCallback(
                    max_retry=1))
    except ImportError as e:  # optuna wraps the driver's ModuleNotFoundError
        missing = getattr(e.__cause__, "name", None) or getattr(e, "name", None) or "?"
        hint = DRIVERS.get(missing, "")
        raise LboError(f"tune.storage: cannot open {shown}: its database driver {missing!r} "
                       f"is not installed{hint}") from e
    except Exception as e:
        reason = (str(getattr(e, "orig", None) or e).strip().splitlines() or [""])[0]
        raise LboError(f"tune.storage: cannot open {shown} ({type(e).__name__}: {reason})") \
            from e


class ClaimLock:
    """A lock, shared by every worker of one study, held from "is a trial still needed?" until
    that trial is RUNNING in the storage, so that workers together start exactly
    ``tune.n_trials`` trials.

    PostgreSQL: a session advisory lock on a connection of its own, which the server drops
    when a killed worker's connection goes. SQLite (one machine): a file lock. Other
    databases: none, and each extra worker may add one trial.
    """

    def __init__(self, storage: optuna.storages.RDBStorage, url: str, study: str) -> None:
        from sqlalchemy.engine import make_url

        self.backend = make_url(url).get_backend_name()
        digest = hashlib.sha1(f"lbo-tune:{study}".encode()).digest()
        self.key = int.from_bytes(digest[:8], "big", signed=True)
        self.engine = storage.engine
        self.file = None
        db = sqlite_path(url) if self.backend == "sqlite" else None
        if db is not None and db.parent.is_dir():  # beside the database, one per study
            from filelock import FileLock

            self.file = FileLock(db.with_name(f"{db.name}.{digest.hex()[:12]}.lock"))
        self.conn = None

    def acquire(self) -> None:
        from sqlalchemy import text

        if self.file is not None:
            self.file.acquire()
        elif self.backend == "postgresql":
            self.conn = self.engine.connect()
            self.conn.execute(text("SELECT pg_advisory_lock(:k)"), {"k": self.key})

    def release(self) -> None:
        """Idempotent: the objective releases it as its trial starts, the loop once more."""
        from sqlalchemy import text

        if self.file is not None and self.file.is_locked:
            self.file.release()
        if self.conn is not None:
            try:
                self.conn.execute(text("SELECT pg_advisory_unlock(:k)"), {"k": self.key})
            finally:
                self.conn.close()
                self.conn = None


def needs_trial(study: optuna.Study, n_trials: int) -> bool:
    """Whether the study needs another trial: fewer than ``n_trials`` finished or running.

    Trials whose worker went silent are failed first (and queued again once, with their
    parameters, for the next ``ask``), so a killed worker's trial does not count as running.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fail_stale_trials is marked experimental
        optuna.storages.fail_stale_trials(study)
    busy = study.get_trials(deepcopy=False, states=(*FINISHED, TrialState.RUNNING))
    return len(busy) < n_trials


