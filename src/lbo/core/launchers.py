"""Hydra's submitit launchers as lbo runs them (``hydra/launcher=submitit_slurm``,
``submitit_local``): the plugin's launchers, with three things added.

- A job that lbo refuses (bad input, a data folder the node cannot reach) ends the sweep in
  that job's one line, exit code 2, as a serial or joblib sweep does, naming the job. The job
  writes the line to its own log and hands it back to the submitting process as a result
  (:class:`JobFailed`), so the submitter learns of it at once, with or without the cluster's
  accounting (sacct).
- A job that ends without a result (cancelled, killed, out of time or memory, its node lost)
  is one line too, with its state, its log and what to do.
- A job given ``cpus_per_task`` CPUs runs its intra-op threads on that many
  (``OMP_NUM_THREADS``, unless set), as joblib's workers get cores / n_jobs: a cluster that
  does not bind jobs to their CPUs would otherwise run every job on all of the node's cores.

:func:`install` (which :func:`lbo.core.cli.ready_launcher` calls for these launchers) has Hydra
build these classes where a config names the plugin's: the configs and records stay the
plugin's own (``hydra.launcher._target_``), and a ``_target_`` of the user's own still wins.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from hydra.core.utils import JobReturn, JobStatus
from hydra_plugins.hydra_submitit_launcher import submitit_launcher as plugin  # type: ignore[import-untyped]

from lbo.core.errors import LboError
from lbo.core.redact import scrub

current_job: str | None = None
"""In a launched job's process: the job, as its one-line error names it (``SLURM job 12_0 on
node-3``); None elsewhere. :func:`lbo.core.cli.entry` reads it to hand an error back rather
than exit."""


class JobFailed(LboError):
    """A launched job's one-line error (its message, and the job that raised it), handed back
    to the submitting process through the job's result."""

    def __init__(self, message: str, job: str) -> None:
        super().__init__(message)
        self.message, self.job = message, job

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.message, self.job))

    def line(self) -> str:
        return f"{self.message} ({self.job})"


def _job_name(executor: str) -> str:
    import submitit

    env = submitit.JobEnvironment()
    if executor == "slurm":
        node = os.environ.get("SLURMD_NODENAME") or env.hostname
        return f"SLURM job {env.job_id} on {node}"
    return f"submitit job {env.job_id}"


def _uncompleted(error: Exception, executor: str) -> str:
    """One line for a job that ended without a result (submitit's UncompletedJobError, whose
    message holds the job's whole error stream)."""
    text = str(error)
    found = re.search(r"Job (\S+) \(task: \d+\) with path (\S+)\s+has not produced any output "
                      r"\(state: ([^)]*)\)", text)
    if found is None:
        return text.strip().splitlines()[0] if text.strip() else type(error).__name__
    job, result, state = found.groups()
    log = re.sub(r"_result\.pkl$", "_log.err", result)
    what = "SLURM job" if executor == "slurm" else "submitit job"
    return (f"{what} {job} ended without a result (state: {state}); its log: {log}. A rerun "
            "of the same command with resume=true reuses the runs that finished and continues "
            "a killed one from its last checkpoint")


class _Lbo:
    """What lbo adds to a submitit launcher (see the module's docstring)."""

    _EXECUTOR: str

    def __call__(self, *args: Any, **kwargs: Any) -> JobReturn:  # in the job's process
        global current_job
        current_job = _job_name(self._EXECUTOR)
        cpus = os.environ.get("SLURM_CPUS_PER_TASK")
        if cpus and cpus.isdigit() and "OMP_NUM_THREADS" not in os.environ:
            os.environ["OMP_NUM_THREADS"] = cpus
            if "torch" in sys.modules:  # imported already: OMP_NUM_THREADS is read at import
                sys.modules["torch"].set_num_threads(int(cpus))
        return super().__call__(*args, **kwargs)  # type: ignore[misc]

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
               ) -> Sequence[JobReturn]:  # in the submitting process
        from submitit.core.utils import UncompletedJobError

        try:
            returns = super().launch(job_overrides, initial_job_idx)  # type: ignore[misc]
        except UncompletedJobError as e:
            _end(_uncompleted(e, self._EXECUTOR))
        for r in returns:
            if r.status is JobStatus.FAILED and isinstance(r._return_value, JobFailed):
                _end(r._return_value.line())
        return returns


def _end(line: str) -> NoReturn:
    """End the submitting command in ``line`` (exit code 2), as :func:`lbo.core.cli.fail`
    does: the sweep's jobs are launched from inside Hydra, which lets only an exit through
    without a traceback."""
    print(f"error: {scrub(line)}", file=sys.stderr, flush=True)
    sys.exit(2)


class SlurmLauncher(_Lbo, plugin.SlurmLauncher):
    """``hydra/launcher=submitit_slurm`` as lbo runs it."""


class LocalLauncher(_Lbo, plugin.LocalLauncher):
    """``hydra/launcher=submitit_local`` as lbo runs it."""



PLUGIN = "hydra_plugins.hydra_submitit_launcher.submitit_launcher"
"""The plugin's module: its launcher classes are ``<PLUGIN>.SlurmLauncher`` and
``<PLUGIN>.LocalLauncher``."""


def install() -> None:
    """Have Hydra build :class:`SlurmLauncher` and :class:`LocalLauncher` where a config names
    the plugin's classes of those names.

    Hydra builds a launcher only from its registry of plugin classes, keyed by class path and
    limited to the ``hydra_plugins`` package; lbo's classes are entered under the plugin's
    paths (``Plugins.class_name_to_class``, the one registry Hydra 1.1 to 1.3 instantiates
    from; ``hydra-core`` is pinned below 1.4, and ``tests/test_slurm.py`` checks that a
    composed ``hydra/launcher=submitit_slurm`` builds lbo's class)."""
    from hydra.core.plugins import Plugins

    registry = Plugins.instance().class_name_to_class
    for cls in (SlurmLauncher, LocalLauncher):
        registry[f"{PLUGIN}.{cls.__name__}"] = cls
