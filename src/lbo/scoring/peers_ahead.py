"""The classical observers scored ahead, in a process of their own, while a training runs.

A training ends by scoring its observer beside the classical ones on the test grid
(:class:`lbo.learn.callbacks.Evaluation`), and their rows are kept beside the test set
(:mod:`lbo.scoring.score_cache`). On a first run they are scored afresh: 45 s on a car that
slips, where the tuned oracle runs the EKF 20 times. A training on fewer torch threads than its
process may use (``threads=1`` on a 2-core machine, as ``experiment=dynamic_carried`` trains)
leaves a core idle: :func:`start` scores them there, into the same kept rows, and the
evaluation reads them back. The kept rows are written whole or not at all, so a process
stopped half way leaves nothing that is read; a peer it did not keep is scored by the
evaluation itself.

    python -m lbo.scoring.peers_ahead '<json: folder, meta, peers, reference>'

is the process's own command; :func:`start` runs it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

from lbo.core.errors import LboError


def spare_core(threads: int) -> bool:
    """Whether a process running torch on ``threads`` intra-op threads leaves a core of its
    own idle: fewer threads than the cores it may use, and no share of the machine set by a
    launcher that runs others beside it (``OMP_NUM_THREADS``: joblib's jobs, pytest-xdist's
    workers), whose other jobs take those cores."""
    if "OMP_NUM_THREADS" in os.environ:
        return False
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return threads < (cores or 1)


class Ahead:
    """The scoring process :func:`start` began: :meth:`wait` for it, or :meth:`stop` it."""

    def __init__(self, process: subprocess.Popen, log: BinaryIO) -> None:
        self.process = process
        self.log = log

    def running(self) -> bool:
        return self.process.poll() is None

    def wait(self) -> str | None:
        """Wait for the process; None when it kept every peer it could, else one line saying
        how it failed (the evaluation then scores what is missing itself)."""
        code = self.process.wait()
        self.log.seek(0)
        lines = self.log.read().decode(errors="replace").strip().splitlines()
        self.log.close()
        if code == 0:
            return None
        return f"exit {code}" + (f": {lines[-1]}" if lines else "")

    def stop(self) -> None:
        """End the process now (a training that failed or was stopped); its kept rows are
        whole files or none."""
        if self.running():
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()


def start(folder: Path, meta: Mapping[str, Any], peers: Sequence[str],
          reference: str) -> Ahead:
    """Score ``peers`` on the test set of the data-set ``folder`` in a process of its own, one
    thread, keeping their rows beside it; ``meta`` holds the ``vehicle`` and ``noise`` the
    observer is trained with (a checkpoint's ``meta``), ``reference`` the NRMSE's E_ref mode."""
    spec = {"folder": str(folder), "vehicle": dict(meta["vehicle"]),
            "noise": dict(meta["noise"]), "peers": list(peers), "reference": reference}
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    log = tempfile.TemporaryFile()
    process = subprocess.Popen([sys.executable, "-m", "lbo.scoring.peers_ahead", json.dumps(spec)],
                               stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log,
                               env=env)
    return Ahead(process, log)


def score(spec: Mapping[str, Any]) -> None:
    """Keep the rows of ``spec["peers"]`` beside the test set of ``spec["folder"]``, as the
    evaluation would score them (:func:`lbo.scoring.grid.classical_table`)."""
    from lbo.models.checkpoint import trained_conditions
    from lbo.scoring.grid import classical_table, load_test, reference
    from lbo.sim.truth import of_folder

    folder = Path(spec["folder"])
    vehicle, noise = trained_conditions(
        {"meta": {"vehicle": spec["vehicle"], "noise": spec["noise"]}}, "(scored ahead)")
    arr = load_test(folder / "test.parquet")
    ref = reference(arr, vehicle, noise, spec["reference"])
    classical_table(arr, vehicle, noise, spec["peers"], ref,
                    truth=of_folder(folder, vehicle.wheelbase), keep=folder / "test.parquet")


if __name__ == "__main__":
    # stopped (Ahead.stop), unwind: a file being kept is then deleted, not left half-written
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        score(json.loads(sys.argv[1]))
    except (LboError, OSError, ValueError) as e:
        sys.exit(f"lbo.scoring.peers_ahead: {e}")
