"""Logs each Python process's CPU time at its exit, for ``benchmarks/process_cpu.py``.

On ``PYTHONPATH`` (``PYTHONPATH=benchmarks/process_cpu``), every interpreter started with
that environment imports it at start: pytest's xdist workers, the commands the tests start,
the SLURM and joblib jobs. Each appends one JSON line to ``$PROCESS_CPU_LOG`` (an absolute
path: the commands run in folders of their own; unset, nothing is logged) at exit: its first
arguments, the test that started it (``PYTEST_CURRENT_TEST``, inherited), its wall
and CPU seconds. A process killed by a signal writes nothing.
"""

import atexit
import json
import os
import resource
import sys
import time

_START = time.time()
_TEST = os.environ.get("PYTEST_CURRENT_TEST", "")
_LOG = os.environ.get("PROCESS_CPU_LOG")


def _log() -> None:
    use = resource.getrusage(resource.RUSAGE_SELF)
    line = {"argv": [str(a)[:200] for a in sys.argv[:4]], "test": _TEST, "pid": os.getpid(),
            "wall": time.time() - _START, "cpu": use.ru_utime + use.ru_stime}
    try:
        # one short append each: the lines of processes that end together stay whole
        with open(str(_LOG), "a") as f:
            f.write(json.dumps(line) + "\n")
    except OSError:
        pass  # a folder the process cannot write: its line is lost, not the process


if _LOG:
    atexit.register(_log)
