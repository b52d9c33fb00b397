"""Where the test suite's CPU goes: a py-spy profile of ``make test``, summed by what it does.

Record it (py-spy is not one of lbo's dependencies: ``pip install py-spy``)::

    py-spy record -r 25 --subprocesses --nonblocking -f raw -o suite.raw -- \\
        .venv/bin/python -m pytest -q -n 2 --dist loadfile -p no:cacheprovider
    python benchmarks/suite_profile.py suite.raw

Each line is the CPU seconds (samples / rate) of the stacks holding a frame that matches the
bucket, across every process py-spy followed (xdist's workers and the commands they start; not
the SLURM jobs, which slurmd starts). Buckets overlap (an ONNX export inside a training counts
in both), so they do not add up to the total. ``--tests PATTERN`` lists, for the stacks holding
a frame that matches PATTERN, the test functions they ran under. ``--processes`` sums the CPU
seconds, and those spent importing, by the command each process ran (xdist's workers, each
``python -m <module>``, the servers), with how many processes ran it.
"""

from __future__ import annotations

import argparse
import re
from collections import Counter
from pathlib import Path

BUCKETS = {
    "imports (any module, any process)": r"^_load_unlocked \(<frozen",
    "ONNX export (torch.onnx.export)": r"^export \(torch/onnx/__init__",
    "Hydra compose": r"^Hydra\.compose_config \(|^compose_config \(hydra/_internal/hydra",
    "Lightning Trainer.fit": r"^Trainer\.fit \(lightning",
    "the evaluation callback (test grid)": r"^Evaluation\.on_fit_end \(lbo",
    "gyro EKF noise fit (gyro_fit.fit)": r"^fit \(lbo/learn/gyro_fit\.py",
    "classical filters (run_stepper)": r"^run_stepper \(lbo/filters",
    "MLflow client calls": r"^MlflowClient\.",
    "Optuna study (lbo.tune)": r"^_run_study \(lbo/tune\.py",
}


def stacks(path: Path):
    """(frames, samples) of each line of a py-spy raw file; a process's command line may hold
    newlines, so a record ends only at a line ending in its sample count."""
    buf = ""
    for line in path.read_text().splitlines():
        buf += line
        if re.search(r" \d+$", buf):
            stack, _, n = buf.rpartition(" ")
            yield stack.split(";"), int(n)
            buf = ""
        else:
            buf += " "


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("raw", type=Path, help="py-spy record -f raw output")
    ap.add_argument("--rate", type=float, default=25.0, help="py-spy's -r (samples per s)")
    ap.add_argument("--tests", help="a frame pattern: list the tests its stacks ran under")
    ap.add_argument("--processes", action="store_true",
                    help="CPU and import seconds by the command each process ran")
    args = ap.parse_args()
    total, buckets, tests = 0, Counter(), Counter()
    cpu, imports = Counter(), Counter()
    patterns = {name: re.compile(p) for name, p in BUCKETS.items()}
    wanted = re.compile(args.tests) if args.tests else None
    for frames, n in stacks(args.raw):
        total += n
        for name, pattern in patterns.items():
            if any(pattern.search(f) for f in frames):
                buckets[name] += n
        if args.processes:
            process = next((f for f in reversed(frames) if f.startswith("process ")), "?")
            cpu[process] += n
            if any(patterns["imports (any module, any process)"].search(f) for f in frames):
                imports[process] += n
        if wanted and any(wanted.search(f) for f in frames):
            under = [f for f in frames if re.match(r"test_\w+.* \(test_\w+\.py", f)]
            tests[re.sub(r":\d+\)$", ")", under[0]) if under else "(no test frame)"] += n
    print(f"{total / args.rate:8.0f} s  every sample")
    for name, n in buckets.most_common():
        print(f"{n / args.rate:8.0f} s  {100 * n / total:4.1f}%  {name}")
    for name, n in tests.most_common(30):
        print(f"{n / args.rate:8.1f} s  {name}")
    if args.processes:
        kinds: dict[str, list[int]] = {}
        for process, n in cpu.items():
            kind = kinds.setdefault(command(process), [0, 0, 0])
            kind[0] += 1
            kind[1] += n
            kind[2] += imports[process]
        print(f"{'processes':>9} {'CPU s':>8} {'imports':>8}  command")
        for name, (count, n, i) in sorted(kinds.items(), key=lambda kv: -kv[1][1])[:25]:
            print(f"{count:9d} {n / args.rate:8.1f} {i / args.rate:8.1f}  {name}")


def command(process: str) -> str:
    """What a py-spy process frame (``process <pid>:"<command line>"``) ran: xdist's workers,
    the module of ``python -m <module>``, or the start of its command line."""
    line = process.split(":", 1)[-1].strip('"')
    if "-c import sys" in line and "execnet" not in line and "-u -c" in line:
        return "python -u -c (xdist's workers)"
    module = re.search(r" -m (\S+)", line)
    return module.group(1) if module else line[:70]


if __name__ == "__main__":
    main()
