"""Where an ``lbo.tune`` study lives: its database, opened with one-line errors and no
password in any line, and the lock under which workers claim trials."""

from __future__ import annotations

import hashlib
import os
import re
import socket
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import optuna
from optuna.trial import FrozenTrial, TrialState

from lbo.core.errors import LboError
from lbo.core.paths import sqlite_path
from lbo.core.redact import MASK, scrub
from lbo.tracking.runs import creation_lock

if TYPE_CHECKING:  # sqlalchemy, imported where a study storage is opened
    from sqlalchemy.engine import Connection

#: Trials that count towards ``tune.n_trials``; failed ones (crashes, killed processes) do not.
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
#: How to install the database drivers that SQLAlchemy asks for.
DRIVERS = {"psycopg": ' (pip install "psycopg[binary]")',
           "psycopg2": " (pip install psycopg2-binary)", "pymysql": " (pip install pymysql)",
           "MySQLdb": " (pip install mysqlclient)"}
#: Connections one worker may hold on a database server: Optuna's queries (the main thread),
#: the heartbeat thread's, and the claim lock's (see :func:`open_storage`).
MAX_CONNECTIONS = 3


def redact(url: str) -> str:
    """The storage URL as it may be printed and logged: without its password (in the URL's
    user part or in a ``?password=`` query parameter)."""
    from sqlalchemy.engine import make_url

    try:
        parsed = make_url(url)
    except Exception as e:  # sqlalchemy.exc.ArgumentError
        # not a URL, but it may still hold a user:password@ part: mask it all the same
        shown = re.sub(r":[^:@/\s]*@", f":{MASK}@", scrub(str(url)))
        raise LboError(f"tune.storage: {shown!r} is not a database URL "
                       f"(sqlite:///path/optuna.db or postgresql://user:pass@host/db)") from e
    return scrub(parsed.render_as_string(hide_password=True))  # scrub: ?password= too


def open_storage(url: str, heartbeat_interval: int,
                 grace_period: int) -> optuna.storages.RDBStorage:
    """Connect to (and if new, initialise) the study database; one line if it cannot.

    A trial whose process stops sending heartbeats for ``grace_period`` s (killed, preempted)
    is marked failed and queued once more with the same parameters.

    On a database server a worker holds at most :data:`MAX_CONNECTIONS` connections: one
    kept open between queries, up to two more while the heartbeat thread and the claim lock
    need theirs. ``tune`` closes them all when it ends (:func:`close_storage`).
    """
    from sqlalchemy.engine import make_url

    shown = redact(url)
    parsed = make_url(url)
    backend = parsed.get_backend_name()
    engine_kwargs: dict[str, Any] = {}
    if backend == "sqlite":
        # workers on one SQLite file wait for each other's writes instead of failing at once
        engine_kwargs = {"connect_args": {"timeout": 60}}
    else:
        # SQLAlchemy's default pool keeps 5 connections and opens 10 more on demand, per
        # process: bounded here, so N workers need N * MAX_CONNECTIONS server slots
        engine_kwargs = {"pool_size": 1, "max_overflow": MAX_CONNECTIONS - 1,
                         "pool_timeout": 120, "pool_pre_ping": True}
        if backend == "postgresql":
            args: dict[str, int | str] = {"connect_timeout": 10}
            if "application_name" not in parsed.query:  # names the worker in pg_stat_activity
                args["application_name"] = f"lbo.tune-{os.getpid()}"
            engine_kwargs["connect_args"] = args
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
        raise LboError(f"tune.storage: cannot open {shown} ({type(e).__name__}: "
                       f"{scrub(reason)})") from e


def close_storage(storage: optuna.storages.RDBStorage) -> None:
    """Close every connection the storage holds (its pool); it reconnects if used again."""
    try:
        storage.remove_session()
    finally:
        storage.engine.dispose()


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
        self.conn: Connection | None = None

    def acquire(self) -> None:
        from sqlalchemy import text

        if self.file is not None:
            self.file.acquire()
        elif self.backend == "postgresql":
            # autocommit: no transaction stays open while the lock is held
            conn = self.engine.connect().execution_options(isolation_level="AUTOCOMMIT")
            try:
                conn.execute(text("SELECT pg_advisory_lock(:k)"), {"k": self.key})
            except BaseException:  # Ctrl-C while waiting: the connection goes all the same
                _drop(conn)
                raise
            self.conn = conn

    def release(self) -> None:
        """Idempotent: the objective releases it as its trial starts, the loop once more. The
        lock's connection goes back to the pool even when the unlock fails."""
        from sqlalchemy import text

        if self.file is not None and self.file.is_locked:
            self.file.release()
        conn, self.conn = self.conn, None
        if conn is not None:
            try:
                conn.execute(text("SELECT pg_advisory_unlock(:k)"), {"k": self.key})
            except BaseException:
                _drop(conn)
                raise
            conn.close()


def _drop(conn: Any) -> None:
    """Close a connection for good, not back into the pool: the server drops any advisory
    lock it may still hold with it."""
    try:
        conn.invalidate()
    finally:
        conn.close()


def worker_id() -> dict[str, str]:
    """The user attributes that name this process as a trial's worker: ``worker``
    (host:pid) and ``worker_start`` (when the process started, to tell a reused pid)."""
    attrs = {"worker": f"{socket.gethostname()}:{os.getpid()}"}
    started = _started(os.getpid())
    if started is not None:
        attrs["worker_start"] = started
    return attrs


def _stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (Linux), or None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat[stat.rindex(")") + 2:].split()  # the command name may hold spaces


def _started(pid: int) -> str | None:
    """The start time of process ``pid`` (clock ticks since boot), or None."""
    fields = _stat(pid)
    return fields[19] if fields is not None and len(fields) > 19 else None


def _gone(attrs: dict[str, Any]) -> bool:
    """Whether the worker named by a trial's user attributes ran on this host and is gone
    (exited, a zombie, or its pid now another process's)."""
    host, _, pid = str(attrs.get("worker", "")).rpartition(":")
    if host != socket.gethostname() or not pid.isdigit():
        return False  # another machine's worker: its heartbeat tells
    number = int(pid)
    if number == os.getpid():
        return False
    try:
        os.kill(number, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        pass
    fields = _stat(number)
    if fields is not None and fields[0] in ("Z", "X"):  # killed, not yet reaped
        return True
    recorded, now = attrs.get("worker_start"), _started(number)
    return recorded is not None and now is not None and recorded != now


def fail_trials(study: optuna.Study, trials: list[FrozenTrial], retry: bool = True) -> list[int]:
    """Mark RUNNING trials failed, as Optuna does for a silent heartbeat (with ``retry``, its
    callback queues each once more with the same parameters). Returns their numbers."""
    storage = study._storage
    failed = []
    for trial in trials:
        try:
            if storage.set_trial_state_values(trial._trial_id, state=TrialState.FAIL):
                failed.append(trial)
        except optuna.exceptions.UpdateFinishedTrialError:
            pass  # finished meanwhile, or failed by another worker
    callback = getattr(storage, "get_heartbeat_stale_trial_callback", lambda: None)()
    if retry and callback is not None:
        for trial in failed:
            callback(study, storage.get_trial(trial._trial_id))
    return [t.number for t in failed]


def fail_dead_trials(study: optuna.Study) -> list[int]:
    """Fail the RUNNING trials whose worker ran on this machine and has exited (killed,
    interrupted) without waiting for their heartbeats to go stale."""
    running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    return fail_trials(study, [t for t in running if _gone(t.user_attrs)])


def fail_own_trials(study: optuna.Study) -> list[int]:
    """Fail the trials this process left RUNNING (interrupted between Optuna's steps)."""
    me = worker_id()["worker"]
    running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    return fail_trials(study, [t for t in running if t.user_attrs.get("worker") == me],
                       retry=False)


def needs_trial(study: optuna.Study, n_trials: int) -> bool:
    """Whether the study needs another trial: fewer than ``n_trials`` finished or running.

    Trials whose worker went silent, or exited on this machine, are failed first (and queued
    again once, with their parameters, for the next ``ask``), so a killed or interrupted
    worker's trial does not count as running.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fail_stale_trials is marked experimental
        optuna.storages.fail_stale_trials(study)
    fail_dead_trials(study)
    busy = study.get_trials(deepcopy=False, states=(*FINISHED, TrialState.RUNNING))
    return len(busy) < n_trials
