"""The Quickstart's observe commands, timed whole: a learned observer against the EKF.

    python benchmarks/bench_observe.py <run id | checkpoint> [--repeats 3]
        [--input examples/stop_and_go_10hz.csv] [--engine auto]

Runs ``python -m lbo.observe observer=<...> input=<log> output=<tmp> plot=true`` for the EKF
and for the given observer, one command at a time, alternating, ``repeats`` times each, and
prints each one's median wall time (start-up, imports, reading, observing, writing, the
figure: what a user waits for) and the ratio of the medians. Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def timed(observer: str, log: str | Path, output: Path, extra: list[str],
          cwd: Path | None = ROOT) -> float:
    """Wall time (s) of one ``python -m lbo.observe observer=<observer> input=<log>
    output=<output> <extra>`` command, run in ``cwd`` (None: this one); its failure is said
    and ends the run."""
    start = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "lbo.observe", f"observer={observer}",
                          f"input={log}", f"output={output}", *extra], capture_output=True,
                         text=True, cwd=cwd)
    wall = time.perf_counter() - start
    if res.returncode != 0:
        sys.exit(f"observer={observer}: {res.stderr.strip().splitlines()[-1]}")
    return wall


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("observer", help="a run id or a checkpoint of a learned observer")
    p.add_argument("--input", default="examples/stop_and_go_10hz.csv")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--engine", default="auto", help="the learned observer's engine=")
    args = p.parse_args()
    times: dict[str, list[float]] = {"ekf": [], args.observer: []}
    with tempfile.TemporaryDirectory(prefix="lbo-observe-") as tmp:
        for _ in range(args.repeats):
            out = Path(tmp) / "estimates.csv"
            times["ekf"].append(timed("ekf", args.input, out, ["plot=true"]))
            times[args.observer].append(timed(args.observer, args.input, out,
                                              ["plot=true", f"engine={args.engine}"]))
    med = {k: statistics.median(v) for k, v in times.items()}
    for name, values in times.items():
        print(f"{name}: median {med[name]:.2f} s ({', '.join(f'{v:.2f}' for v in values)})")
    print(f"ratio: {med[args.observer] / med['ekf']:.2f} times the EKF's time "
          f"(engine={args.engine}, {args.repeats} runs each, {args.input})")


if __name__ == "__main__":
    main()
