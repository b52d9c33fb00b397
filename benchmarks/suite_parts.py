"""Where each test's time goes, by part: a pytest plugin that times, per test, the ONNX exports
(dynamo and TorchScript-based), TorchScript traces, Lightning's ``Trainer.fit`` in the test's
process, the gyro EKF's noise fits and the waits on subprocesses (the commands a test starts,
the sweeps, the SLURM jobs), MLflow opening SQL stores (and building new ones' tables), Hydra's
composes, and a summary of what it wrote.

    PYTHONPATH=benchmarks .venv/bin/python -m pytest -q -n 2 --dist loadfile \\
        -p suite_parts -p no:cacheprovider          # writes reports/suite_parts.jsonl
    python benchmarks/suite_parts.py reports/suite_parts.jsonl [--top 15]

Each line of the file is one test that spent time in a part: its node id and, per part, the
seconds and the calls. Parts nest (an export inside a fit counts in both); a subprocess's
time is its wall time, whatever it ran. Unlike ``suite_profile.py`` (py-spy, CPU by stack), it
needs nothing installed and names the test.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

OUT = Path(os.environ.get("SUITE_PARTS", "reports/suite_parts.jsonl"))
_now: dict[str, Any] = {"id": None}
_spent: dict[str, dict[str, list[float]]] = {}


_open: set[str] = set()
"""The parts being timed now: a part called inside itself (``communicate`` calls ``wait``)
counts once."""


def _timed(owner: Any, name: str, part: str) -> None:
    inner = getattr(owner, name)

    @functools.wraps(inner)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if part in _open:
            return inner(*args, **kwargs)
        _open.add(part)
        start = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            _open.discard(part)
            slot = _spent.setdefault(_now["id"], {}).setdefault(part, [0.0, 0])
            slot[0] += time.perf_counter() - start
            slot[1] += 1

    setattr(owner, name, wrapper)


def pytest_configure(config: Any) -> None:
    """Wrap the parts before any test module imports them by name."""
    import lightning.pytorch as pl
    from hydra._internal.hydra import Hydra
    from mlflow.store.db import utils as mlflow_db
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    from lbo.learn import gyro_fit
    from lbo.serve import engines

    for owner, name, part in ((engines, "dynamo_onnx", "dynamo export"),
                              (engines, "legacy_onnx", "TorchScript-based export"),
                              (engines, "trace", "TorchScript trace"),
                              (pl.Trainer, "fit", "Trainer.fit in-process"),
                              (gyro_fit, "fit", "gyro noise fit"),
                              (mlflow_db, "_initialize_tables", "MLflow builds a new store"),
                              (SqlAlchemyStore, "__init__", "MLflow opens a SQL store"),
                              (Hydra, "compose_config", "Hydra compose"),
                              (subprocess.Popen, "communicate", "subprocess wait"),
                              (subprocess.Popen, "wait", "subprocess wait")):
        _timed(owner, name, part)


def pytest_runtest_protocol(item: Any, nextitem: Any) -> None:
    _now["id"] = item.nodeid


def pytest_runtest_logfinish(nodeid: str, location: Any) -> None:
    spent = _spent.pop(nodeid, None)
    if spent:
        OUT.parent.mkdir(parents=True, exist_ok=True)
        with OUT.open("a") as f:  # one short line per test: the workers' appends do not mix
            f.write(json.dumps({"id": nodeid, **spent}) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report", type=Path)
    ap.add_argument("--top", type=int, default=10)
    args = ap.parse_args()
    total: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    tests: dict[str, dict[str, float]] = defaultdict(dict)
    for line in args.report.read_text().splitlines():
        row = json.loads(line)
        test = row.pop("id")
        for part, (seconds, calls) in row.items():
            total[part][0] += seconds
            total[part][1] += calls
            tests[part][test] = seconds
    for part, (seconds, calls) in sorted(total.items(), key=lambda kv: -kv[1][0]):
        print(f"{seconds:7.0f} s  {int(calls):5d} calls  {part}")
        for test, s in sorted(tests[part].items(), key=lambda kv: -kv[1])[:args.top]:
            print(f"          {s:6.1f} s  {test}")


if __name__ == "__main__":
    main()
