"""Parallel trainings on one machine: does a second job at once gain, or does it stall both?

    python benchmarks/bench_threads.py [--jobs 2] [--repeats 3] [--set trainer.max_epochs=4 ...]

Each case starts ``python -m lbo.train experiment=smoke`` processes at once (each in its own
temporary folder and MLflow store, the smoke data set shared) and times the batch from the
first start to the last exit (whole commands: start-up, data, training, evaluation):

- ``1 job``: one process, torch's default threads (all cores);
- ``N jobs, default threads``: N processes at once, each taking every core (what two
  ``lbo.tune`` workers started by hand do);
- ``N jobs, threads=cores/N``: N processes at once, each told its share (``threads=``; what
  ``hydra/launcher=joblib`` gives its jobs by itself).

Prints, per case, the median wall time of the batch over ``repeats`` and the time per job
(wall / jobs): two jobs at once should take no longer a job than one alone.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def batch(jobs: int, threads: int | None, extra: list[str], data_root: Path) -> float:
    """Wall time (s) of ``jobs`` smoke trainings started together."""
    with tempfile.TemporaryDirectory(prefix="lbo-threads-") as tmp:
        env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{Path(tmp) / 'mlflow.db'}"}
        env.pop("OMP_NUM_THREADS", None)
        start = time.perf_counter()
        procs = [subprocess.Popen(
            [sys.executable, "-m", "lbo.train", "experiment=smoke", f"data.root={data_root}",
             f"hydra.run.dir={Path(tmp) / str(i)}",
             *([f"threads={threads}"] if threads else []), *extra],
            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            for i in range(jobs)]
        for p in procs:
            _, err = p.communicate()
            if p.returncode:
                raise SystemExit(f"a training failed:\n{err[-2000:]}")
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--set", nargs="*", default=[], help="more training overrides")
    args = parser.parse_args()
    cores = len(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory(prefix="lbo-threads-data-") as data:
        batch(1, None, args.set, Path(data))  # generates the smoke set once, outside the timing
        cases = [("1 job", 1, None), (f"{args.jobs} jobs, default threads", args.jobs, None),
                 (f"{args.jobs} jobs, threads={max(1, cores // args.jobs)}", args.jobs,
                  max(1, cores // args.jobs))]
        walls: dict[str, list[float]] = {name: [] for name, _, _ in cases}
        for _ in range(args.repeats):  # the cases alternate: they share the machine's drift
            for name, jobs, threads in cases:
                walls[name].append(batch(jobs, threads, args.set, Path(data)))
    print(f"{cores} cores; python -m lbo.train experiment=smoke {' '.join(args.set)}; "
          f"median of {args.repeats}")
    print("| case | wall (s) | per job (s) |\n|---|---:|---:|")
    for name, jobs, _ in cases:
        wall = statistics.median(walls[name])
        print(f"| {name} | {wall:.1f} | {wall / jobs:.1f} |")


if __name__ == "__main__":
    main()
