"""A real one-node SLURM cluster for the tests: munged, slurmctld and slurmd in a temporary folder
of their own, on 127.0.0.1 and free ports, stopped (with every job and process they started) when
the test ends, pass or fail.

Debian packages SLURM as ``slurm-wlm`` with ``munge`` (``.ci/run`` installs them when missing).
The daemons run as the user who runs the tests (root, as on CI; slurmd starts jobs as their
submitter). The cluster has no accounting database (slurmdbd): each job's end is written to its
job completion log (``jobcomp/filetxt``), which :meth:`Slurm.completed` reads, and which the
cluster's ``sacct`` (``<folder>/bin/sacct``, first on :attr:`Slurm.env`'s PATH) answers from, as
``sacct --completion`` does, so that submitit learns a job's end state (COMPLETED, FAILED,
CANCELLED) as it does from a cluster's accounting.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from helpers.servers import free_port

DAEMONS = ("munged", "slurmctld", "slurmd", "unshare")
COMMANDS = ("sbatch", "srun", "squeue", "sacct", "scancel", "scontrol", "sinfo")
NODE = "lbo-node"
PARTITION = "lbo"


def missing_programs() -> list[str]:
    """The SLURM and munge programs not on PATH (nor in /usr/sbin)."""
    path = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"])
    return [p for p in (*DAEMONS, *COMMANDS) if shutil.which(p, path=path) is None]


def program(name: str) -> str:
    found = shutil.which(name, path=os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin",
                                                     "/sbin"]))
    if found is None:
        pytest.fail(f"{name} not found: install SLURM (apt-get install slurm-wlm munge; "
                    ".ci/run does)")
    return found


@dataclass
class Slurm:
    folder: Path
    conf: Path
    env: dict[str, str]
    """What a command run against this cluster adds to the environment: ``SLURM_CONF`` and a
    PATH that finds the cluster's ``sacct`` first. sbatch hands the submitter's environment
    to its jobs, so the jobs have them too."""

    def command(self, *args: str, timeout: float = 60, check: bool = True
                ) -> subprocess.CompletedProcess:
        """A SLURM client command (``squeue``, ``scancel``, ...) against this cluster."""
        res = subprocess.run([program(args[0]), *args[1:]], capture_output=True, text=True,
                             timeout=timeout, env={**os.environ, **self.env})
        if check and res.returncode != 0:
            pytest.fail(f"{' '.join(args)} failed: {res.stderr.strip()}")
        return res

    def completed(self) -> list[dict[str, str]]:
        """Every job that ended, from the job completion log, in order: ``JobId``,
        ``JobState`` (COMPLETED, FAILED, CANCELLED, ...), ``Name``, ``NodeList``, ``ExitCode``,
        ``WorkDir``, ..."""
        log = self.folder / "jobcomp.log"
        if not log.is_file():
            return []
        jobs = []
        for line in log.read_text().splitlines():
            fields: dict[str, str] = {}
            for item in line.split(" "):
                key, sep, value = item.partition("=")
                if sep:
                    fields[key] = value
            if fields:
                jobs.append(fields)
        return jobs

    def ended(self) -> dict[str, dict[str, str]]:
        """:meth:`completed`, by the id submitit gives each job (``<array job>_<task>`` for a
        task of an array, as each of a sweep's jobs is)."""
        return {(f"{j['ArrayJobId']}_{j['ArrayTaskId']}" if j.get("ArrayJobId") else
                 j["JobId"]): j for j in self.completed()}

    def queue(self) -> list[dict[str, str]]:
        """The jobs pending or running now: ``id``, ``state``, ``name``."""
        out = self.command("squeue", "-h", "-o", "%i|%T|%j").stdout
        return [dict(zip(("id", "state", "name"), line.split("|"), strict=True))
                for line in out.splitlines() if line.strip()]

    def wait_empty(self, timeout: float = 60) -> None:
        """Wait until no job is pending or running (a job's result reaches its submitter a
        moment before the job's own process has ended)."""
        deadline = time.monotonic() + timeout
        while self.queue():
            if time.monotonic() > deadline:
                pytest.fail(f"jobs still queued after {timeout:.0f} s: {self.queue()}")
            time.sleep(0.5)

    def logs(self) -> str:
        """The daemons' logs' tails, for a failure message."""
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-2000:]}"
                         for p in sorted(self.folder.glob("*.log")))


def _write_conf(folder: Path, user: str, ctld_port: int, slurmd_port: int, cpus: int) -> Path:
    host = socket.gethostname().split(".")[0]  # slurmctld runs only where SlurmctldHost names
    conf = folder / "slurm.conf"
    (folder / "plugstack.conf").write_text("")  # no SPANK plug-ins of the machine's
    conf.write_text("\n".join([
        "ClusterName=lbo-test",
        f"SlurmctldHost={host}(127.0.0.1)",
        f"SlurmctldPort={ctld_port}",
        f"SlurmdPort={slurmd_port}",
        # bind every daemon, and srun, to the address a name resolves to, never 0.0.0.0
        "CommunicationParameters=NoCtldInAddrAny,NoInAddrAny",
        f"SlurmUser={user}",
        f"SlurmdUser={user}",
        "AuthType=auth/munge",
        "CredType=cred/munge",
        f"AuthInfo=socket={folder / 'munge.socket'}",
        f"StateSaveLocation={folder / 'state'}",
        f"SlurmdSpoolDir={folder / 'spool'}",
        f"SlurmctldPidFile={folder / 'slurmctld.pid'}",
        f"SlurmdPidFile={folder / 'slurmd.pid'}",
        f"SlurmctldLogFile={folder / 'slurmctld.log'}",
        f"SlurmdLogFile={folder / 'slurmd.log'}",
        f"PlugStackConfig={folder / 'plugstack.conf'}",
        "ProctrackType=proctrack/linuxproc",
        "TaskPlugin=task/none",
        "JobAcctGatherType=jobacct_gather/none",
        "AccountingStorageType=accounting_storage/none",
        "JobCompType=jobcomp/filetxt",
        f"JobCompLoc={folder / 'jobcomp.log'}",
        "SelectType=select/cons_tres",
        "SelectTypeParameters=CR_CPU",
        "MpiDefault=none",
        "SwitchType=switch/none",
        "ReturnToService=2",
        "MailProg=/bin/true",
        "KillWait=5",           # a cancelled job: SIGTERM, then SIGKILL 5 s later
        "MinJobAge=300",        # scontrol show job knows an ended job for 5 minutes
        "SlurmctldTimeout=30",
        "SlurmdTimeout=60",
        f"NodeName={NODE} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory=1024 State=UNKNOWN",
        f"PartitionName={PARTITION} Nodes={NODE} Default=YES MaxTime=INFINITE State=UP",
        ""]))
    return conf


def _environ_of(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:
        return b""


def _stragglers(conf: Path) -> list[int]:
    """The processes, other than this one, whose environment names this cluster's config:
    its daemons, slurmstepd and the jobs (sbatch hands them the submitter's environment)."""
    mark = f"SLURM_CONF={conf}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid() and \
                mark in _environ_of(int(entry.name)).split(b"\0"):
            found.append(int(entry.name))
    return found


@contextlib.contextmanager
def slurm_cluster(cpus: int = 2, unmounted: Path | None = None, timeout: float = 60
                  ) -> Iterator[Slurm]:
    """A one-node SLURM cluster (node :data:`NODE`, ``cpus`` CPUs, partition
    :data:`PARTITION`), up once ``sinfo`` shows its node idle; stopped when the block ends,
    pass or fail: its jobs cancelled, its daemons and every process that carries its
    ``SLURM_CONF`` killed, its folder removed.

    ``unmounted``: a folder of this machine that the node does not reach, as a shared file
    system that a node lacks: slurmd, and so every job, runs in a mount namespace of its own
    where an empty read-only file system covers that folder."""
    missing = missing_programs()
    if missing:
        pytest.fail(f"{', '.join(missing)} not found: install SLURM (apt-get install "
                    "slurm-wlm munge; .ci/run does)")
    if os.geteuid() != 0:
        pytest.fail("the SLURM tests run the cluster's daemons as root (slurmd starts each job "
                    "as its submitter; the node's mount namespace needs it too): run them as "
                    "root, as CI does")
    user = pwd.getpwuid(os.getuid()).pw_name
    folder = Path(tempfile.mkdtemp(prefix="lbo-slurm-"))  # 0700: munged checks its key's folder
    for sub in ("state", "spool", "bin"):
        (folder / sub).mkdir()
    key = folder / "munge.key"
    key.write_bytes(os.urandom(1024))
    key.chmod(0o400)
    conf = _write_conf(folder, user, free_port(), free_port(), cpus)
    sacct = folder / "bin" / "sacct"
    sacct.write_text(f"#!/bin/sh\nexec {program('sacct')} --completion \"$@\"\n")
    sacct.chmod(0o755)
    env = {"SLURM_CONF": str(conf),
           "PATH": os.pathsep.join([str(folder / "bin"), os.environ.get("PATH", ""),
                                    "/usr/sbin"])}
    daemon_env = {**os.environ, **env}
    procs: list[subprocess.Popen] = []
    logs = []
    cluster = Slurm(folder, conf, env)

    def start(name: str, *args: str) -> None:
        log = open(folder / f"{name}.out", "w")
        logs.append(log)
        procs.append(subprocess.Popen([program(name), *args], stdout=log,
                                      stderr=subprocess.STDOUT, start_new_session=True,
                                      cwd=folder, env=daemon_env))

    try:
        start("munged", "--foreground", "--force", f"--socket={folder / 'munge.socket'}",
              f"--key-file={key}", f"--pid-file={folder / 'munged.pid'}",
              f"--log-file={folder / 'munged.log'}", f"--seed-file={folder / 'munged.seed'}")
        _wait(lambda: (folder / "munge.socket").exists(), timeout, "munged", cluster, procs)
        start("slurmctld", "-D", "-i")
        if unmounted is None:
            start("slurmd", "-D", "-N", NODE)
        else:  # unshare execs slurmd in the namespace: the same process
            start("unshare", "--mount", "--propagation", "private", "sh", "-c",
                  f'mount -t tmpfs -o ro,size=64k unmounted "$0" && exec "$1" -D -N {NODE}',
                  str(unmounted), program("slurmd"))

        def idle() -> bool:
            res = cluster.command("sinfo", "-h", "-N", "-o", "%T", check=False, timeout=10)
            return res.returncode == 0 and res.stdout.strip() == "idle"

        _wait(idle, timeout, "the SLURM node", cluster, procs)
        yield cluster
    finally:
        _stop(cluster, procs)
        for log in logs:
            log.close()
        shutil.rmtree(folder, ignore_errors=True)


def _wait(ready, timeout: float, what: str, cluster: Slurm, procs: list[subprocess.Popen]
          ) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        dead = [p.args[0] for p in procs if p.poll() is not None]
        if dead or time.monotonic() > deadline:
            outs = "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-2000:]}"
                             for p in sorted(cluster.folder.glob("*.out")))
            pytest.fail(f"{what} did not come up within {timeout:.0f} s"
                        + (f" ({', '.join(dead)} exited)" if dead else "")
                        + f":\n{outs}\n{cluster.logs()}")
        time.sleep(0.2)


def _stop(cluster: Slurm, procs: list[subprocess.Popen]) -> None:
    """Cancel every job, stop the daemons, then kill whatever still carries the cluster's
    SLURM_CONF (a job's processes, a slurmstepd), each by its pid."""
    with contextlib.suppress(Exception):
        if any(p.poll() is None for p in procs[1:]):
            ids = [j["id"] for j in cluster.queue()]
            if ids:
                cluster.command("scancel", *ids, check=False, timeout=20)
                deadline = time.monotonic() + 20
                while cluster.queue() and time.monotonic() < deadline:
                    time.sleep(0.5)
            cluster.command("scontrol", "shutdown", check=False, timeout=20)
    for proc in reversed(procs):  # slurmd, slurmctld, then munged
        if proc.poll() is None and not proc.args[0].endswith("munged"):
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=10)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM if proc.poll() is None else signal.SIGKILL)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    for pid in _stragglers(cluster.conf):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
