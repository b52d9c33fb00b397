"""How long each test file and test takes, from a JUnit XML report: the order the suite runs
the files in, and which tests ``make test-fast`` leaves out.

    .venv/bin/python -m pytest -n 2 --junitxml=reports/tests.xml   # any run of the suite
    python benchmarks/test_durations.py reports/tests.xml          # -> tests/durations.json
    python benchmarks/test_durations.py reports/tests.xml --top 30 # also the 30 slowest tests
    python benchmarks/test_durations.py reports/tests.xml reports/fast.xml  # and test-fast's run

``make test`` hands whole files to its two xdist workers (``--dist loadfile``: a file's
module fixtures, a trained observer or a server, are made once), each worker taking the next
file when it is free. Taken in collection order, a long file that comes last keeps one worker
busy after the other has finished; ``tests/conftest.py`` therefore hands them out longest
first (the LPT rule), by the seconds this script writes into ``tests/durations.json`` (setup,
call and teardown summed per file). A file not listed there goes first, as if it were long.
The file also lists each test that took at least :data:`LISTED_S` seconds: ``tests/conftest.py``
marks those of them over its ``SLOW_S`` as ``slow``, which ``make test-fast`` skips.
"""

from __future__ import annotations

import argparse
import json
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

OUT = Path(__file__).resolve().parent.parent / "tests" / "durations.json"
LISTED_S = 1.0
"""Seconds from which a test is listed by name (the others only count in their file's sum)."""


def per_test(report: Path) -> dict[str, float]:
    """Seconds per test (``file::name``) of a JUnit XML report written by pytest."""
    times: dict[str, float] = {}
    for case in ET.parse(report).getroot().iter("testcase"):
        parts = case.get("classname", "").split(".")  # tests.test_x(.TestClass)
        n = next((i for i, part in enumerate(parts) if part.startswith("test_")), len(parts) - 1)
        file = "/".join(parts[:n + 1]) + ".py"
        times[f"{file}::{case.get('name')}"] = float(case.get("time", 0.0))
    return times


def per_file(times: dict[str, float]) -> dict[str, float]:
    """Seconds per test file, summed over its tests, longest first."""
    files: dict[str, float] = defaultdict(float)
    for test, seconds in times.items():
        files[test.split("::")[0]] += seconds
    return dict(sorted(((f, round(s, 1)) for f, s in files.items()), key=lambda x: -x[1]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("report", type=Path, help="pytest's --junitxml report of the whole suite")
    p.add_argument("more", type=Path, nargs="*",
                   help="reports of other runs (make test-fast's): a test is listed by the "
                        "longest it took in any (its module's fixtures are charged to whichever "
                        "of its tests comes first, which differs between runs)")
    p.add_argument("--top", type=int, default=0, help="also print the N slowest tests")
    p.add_argument("--out", type=Path, default=OUT, help="where the per-file seconds go")
    args = p.parse_args()
    times = per_test(args.report)
    files = per_file(times)
    longest = dict(times)
    for more in args.more:
        for test, seconds in per_test(more).items():
            longest[test] = max(seconds, longest.get(test, 0.0))
    tests = {t: round(s, 1) for t, s in sorted(longest.items(), key=lambda x: -x[1])
             if s >= LISTED_S and t in times}
    args.out.write_text(json.dumps({"files": files, "tests": tests}, indent=1) + "\n")
    print(f"{len(times)} tests in {len(files)} files, {sum(times.values()):.0f} s summed; "
          f"per file, and the {len(tests)} tests of {LISTED_S:g} s or more -> {args.out}")
    for test, seconds in sorted(times.items(), key=lambda x: -x[1])[:args.top]:
        print(f"{seconds:8.1f} s  {test}")


if __name__ == "__main__":
    main()
