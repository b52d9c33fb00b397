"""CPU time of every Python process of a test run, by kind: the pytest workers, and the
commands they start (``lbo.train``, ``lbo.tune``, submitit's SLURM jobs, joblib's workers ...).

    PROCESS_CPU_LOG=$PWD/reports/process_cpu.jsonl PYTHONPATH=benchmarks/process_cpu \\
        .venv/bin/python -m pytest -q -n 2 --dist loadfile -p no:cacheprovider
    python benchmarks/process_cpu.py reports/process_cpu.jsonl [--top 15]

``benchmarks/process_cpu/sitecustomize.py`` writes the log. A process killed by a signal
(the tests' killed runs) is not in it, so the sum is a floor.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path


def kind(argv: list[str], test: str = "") -> str:
    """What a process was: an xdist worker (``-c``, started before any test), a test's
    ``python -c`` script, a module run with ``-m`` or a script, by its file's name."""
    if not argv:
        return "?"
    first = argv[0]
    if first == "-c":
        return "python -c (a test's script)" if test else "pytest-xdist worker"
    name = Path(first).name
    if name in ("__main__.py", "_submit.py", "_local.py"):
        return Path(first).parent.name if name == "__main__.py" else f"submitit {name}"
    return name


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--top", type=int, default=15, help="processes listed, most CPU first")
    args = ap.parse_args()
    rows = [json.loads(line) for line in args.log.read_text().splitlines() if line.strip()]
    by_kind: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    for r in rows:
        k = by_kind[kind(r["argv"], r["test"])]
        k[0] += r["cpu"]
        k[1] += 1
    total = sum(r["cpu"] for r in rows)
    print(f"{len(rows)} processes, {total:.0f} CPU-s")
    for name, (cpu, n) in sorted(by_kind.items(), key=lambda kv: -kv[1][0]):
        print(f"{cpu:8.0f} s  {n:4d}  {name}")
    print("most CPU:")
    for r in sorted(rows, key=lambda r: -r["cpu"])[:args.top]:
        print(f"{r['cpu']:8.1f} s  {kind(r['argv'], r['test'])}  {r['test'][:90]}")


if __name__ == "__main__":
    main()
