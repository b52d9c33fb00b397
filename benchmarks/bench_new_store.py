"""A new SQLite MLflow store: built by MLflow's migrations, or copied from lbo's empty one.

    python benchmarks/bench_new_store.py [--repeats 5]

Each case opens a new file and lists its experiments, in a fresh process each time (MLflow
keeps the stores it opened for the life of a process), and prints the median seconds over
``repeats``, the import of MLflow left out:

- ``MLflow builds it``: ``MlflowClient(<new file>)``, as MLflow does without lbo;
- ``lbo copies it``: :func:`lbo.tracking.new_store.seed` first (the empty store already in
  the cache, as after a project's first store), then the same client.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CASE = """
import sys, time
import mlflow
from mlflow import MlflowClient
from lbo.tracking.new_store import seed
uri = "sqlite:///" + sys.argv[1]
start = time.perf_counter()
if sys.argv[2] == "seed":
    seed(uri)
MlflowClient(uri).search_experiments()
print(time.perf_counter() - start)
"""


def once(folder: Path, name: str, how: str, env: dict[str, str]) -> float:
    res = subprocess.run([sys.executable, "-c", CASE, str(folder / name), how],
                         capture_output=True, text=True, env=env, check=True)
    return float(res.stdout.strip().splitlines()[-1])


def main() -> None:
    import os

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        env = {**os.environ, "LBO_CACHE_DIR": str(folder / "cache")}
        once(folder, "warm.db", "seed", env)  # the cache's empty store, made once
        for label, how in (("MLflow builds it", "plain"), ("lbo copies it", "seed")):
            times = [once(folder, f"{how}{i}.db", how, env) for i in range(args.repeats)]
            print(f"{label:18s} median {statistics.median(times):.3f} s over {args.repeats} "
                  f"(min {min(times):.3f}, max {max(times):.3f})")


if __name__ == "__main__":
    main()
