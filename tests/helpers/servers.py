"""Real servers for the tests: PostgreSQL and an MLflow tracking server, each on 127.0.0.1, on a
free port, in a temporary folder of its own, and stopped when the test ends, pass or fail."""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

PG_USER = "lbo"
PG_PASSWORD = "pg-test-pw-7f3a"  # a throwaway password, so the tests can look for leaks


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pg_binary(name: str) -> str:
    """A PostgreSQL server program (initdb, pg_ctl) from PATH or Debian's install folder."""
    found = shutil.which(name) or next(iter(sorted(glob.glob(
        f"/usr/lib/postgresql/*/bin/{name}"), reverse=True)), None)
    if found is None:
        pytest.fail(f"{name} not found: install the PostgreSQL server (.ci/run does)")
    return found


@dataclass
class Postgres:
    port: int
    folder: Path

    def url(self, password: str = PG_PASSWORD, database: str = "postgres") -> str:
        return f"postgresql://{PG_USER}:{password}@127.0.0.1:{self.port}/{database}"

    def connections(self, settle_s: float = 10) -> dict[str, tuple[int, int]]:
        """Per client application_name: ``(peak, open)``, the most connections it held at
        once and how many it holds now, exactly, from the server's connection log.

        A backend logs its disconnection just after its client went: while any client still
        holds one, the log is read again, for up to ``settle_s`` seconds."""
        deadline = time.monotonic() + settle_s
        while True:
            found = self._connections()
            if time.monotonic() > deadline or not any(now for _, now in found.values()):
                return found
            time.sleep(0.1)

    def _connections(self) -> dict[str, tuple[int, int]]:
        app_of: dict[str, str] = {}
        now: dict[str, int] = {}
        peak: dict[str, int] = {}
        log = (self.folder / "server.log").read_text(errors="replace")
        for line in log.splitlines():
            m = re.search(r"\[(\d+)\] LOG:  connection authorized: .*?"
                          r"(?:application_name=(\S+))?$", line)
            if m:
                app = app_of[m[1]] = m[2] or ""
                now[app] = now.get(app, 0) + 1
                peak[app] = max(peak.get(app, 0), now[app])
                continue
            m = re.search(r"\[(\d+)\] LOG:  disconnection: ", line)
            if m and m[1] in app_of:
                now[app_of.pop(m[1])] -= 1
        return {app: (peak[app], now[app]) for app in peak}


@contextlib.contextmanager
def postgres(max_connections: int = 50,
             superuser_reserved_connections: int = 3) -> Iterator[Postgres]:
    """A PostgreSQL server with password authentication for user ``lbo``, which logs every
    connection and disconnection (see :meth:`Postgres.connections`).

    The server refuses to run as root: as root it runs as the ``postgres`` system user, in a
    folder handed to that user. ``lbo`` is the server's superuser: it may use the
    ``superuser_reserved_connections`` too, all ``max_connections`` slots.
    """
    user = None
    if os.geteuid() == 0:
        user = "postgres"
        try:
            pw = pwd.getpwnam(user)
        except KeyError:
            pytest.fail("running as root needs the 'postgres' system user (.ci/run creates it)")
    folder = Path(tempfile.mkdtemp(prefix="lbo-pg-"))
    data, port = folder / "data", free_port()
    if user is not None:
        os.chown(folder, pw.pw_uid, pw.pw_gid)

    def run(*args: str, **kw) -> subprocess.CompletedProcess:
        return subprocess.run(list(args), user=user, cwd=folder, capture_output=True,
                              text=True, timeout=120, **kw)

    pwfile = folder / "pw"
    pwfile.write_text(PG_PASSWORD + "\n")
    if user is not None:
        os.chown(pwfile, pw.pw_uid, pw.pw_gid)
    started = False
    try:
        out = run(pg_binary("initdb"), "-D", str(data), "-U", PG_USER, f"--pwfile={pwfile}",
                  "--auth=scram-sha-256", "-E", "UTF8", "--no-locale")
        assert out.returncode == 0, out.stderr
        opts = (f"-p {port} -c listen_addresses=127.0.0.1 -k {folder} "
                f"-c max_connections={max_connections} "
                f"-c superuser_reserved_connections={superuser_reserved_connections} "
                "-c log_connections=on -c log_disconnections=on "
                "-c log_line_prefix='%m [%p] '")
        out = run(pg_binary("pg_ctl"), "-D", str(data), "-o", opts, "-l",
                  str(folder / "server.log"), "-w", "-t", "60", "start")
        started = True
        assert out.returncode == 0, out.stderr + (folder / "server.log").read_text()
        yield Postgres(port, folder)
    finally:
        if started:
            run(pg_binary("pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop")
        shutil.rmtree(folder, ignore_errors=True)


@dataclass
class MlflowServer:
    url: str
    folder: Path


@contextlib.contextmanager
def _http_server(args: list[str], folder: Path, probe: str, what: str, timeout: float,
                 env: dict[str, str] | None = None) -> Iterator[str]:
    """Start ``python -m <args>`` (listening on 127.0.0.1:<port> as ``args`` say) in
    ``folder``; yield its URL once ``probe`` answers 200, and stop it (and remove ``folder``)
    when the block ends, pass or fail."""
    import requests

    port = free_port()
    log = open(folder / "server.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", *(a.replace("{port}", str(port)) for a in args)],
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                            cwd=folder, env=env)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            with contextlib.suppress(requests.RequestException):
                if requests.get(f"{url}/{probe}", timeout=2).status_code == 200:
                    break
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"{what} did not start:\n"
                            + (folder / "server.log").read_text()[-3000:])
            time.sleep(0.5)
        yield url
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def mlflow_server(backend: str | None = None) -> Iterator[MlflowServer]:
    """``mlflow server`` with a SQLite backend store (or ``backend``) and an artifact root of
    its own, serving the artifacts itself (clients upload and download through it)."""
    from lbo.tracking.new_store import seed

    folder = Path(tempfile.mkdtemp(prefix="lbo-mlflow-"))
    backend = backend or f"sqlite:///{folder / 'mlflow.db'}"
    seed(backend)  # lbo's empty store, not the server's 3 s of migrations
    args = ["mlflow", "server", "--host", "127.0.0.1", "--port", "{port}",
            "--backend-store-uri", backend, "--artifacts-destination", str(folder / "artifacts"),
            "--workers", "1"]
    # no job runner: lbo queues no server-side job, and its huey consumers took 60 s of CPU
    # over one run of the suite (py-spy)
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    with _http_server(args, folder, "health", "mlflow server", 120, env) as url:
        yield MlflowServer(url, folder)


@contextlib.contextmanager
def model_server(model_uri: str, env: dict[str, str]) -> Iterator[str]:
    """``mlflow models serve`` of ``model_uri`` with ``--env-manager local`` on 127.0.0.1 and a
    free port, in a folder of its own; yields its URL, and stops it when the test ends."""
    folder = Path(tempfile.mkdtemp(prefix="lbo-serve-"))
    # mlflow starts its scoring server as `uvicorn` through a shell, so this interpreter's
    # scripts folder goes first on PATH even when no virtual environment is activated
    scripts = str(Path(sys.executable).parent)
    env = {**env, "PATH": os.pathsep.join([scripts, env.get("PATH", "")])}
    args = ["mlflow", "models", "serve", "-m", model_uri, "--env-manager", "local", "-h",
            "127.0.0.1", "-p", "{port}", "-w", "1"]
    with _http_server(args, folder, "ping", "mlflow models serve", 180, env) as url:
        yield url
