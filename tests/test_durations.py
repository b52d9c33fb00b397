"""The suite's own bookkeeping: seconds per file and per test from a JUnit report
(benchmarks/test_durations.py), and the tests ``make test-fast`` leaves out by them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from conftest import SLOW_S

from helpers.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
REPORT = """<?xml version="1.0" encoding="utf-8"?><testsuites><testsuite name="pytest">
<testcase classname="tests.test_a" name="test_one" time="2.5"/>
<testcase classname="tests.test_a" name="test_two[x]" time="0.5"/>
<testcase classname="tests.test_b.TestGroup" name="test_three" time="1.0"/>
</testsuite></testsuites>"""


def test_a_report_gives_seconds_per_file_and_the_tests_of_a_second_or_more(tmp_path,
                                                                            monkeypatch):
    (tmp_path / "tests.xml").write_text(REPORT)
    out = tmp_path / "durations.json"
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "test_durations.py"),
                          str(tmp_path / "tests.xml"), "--out", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert json.loads(out.read_text()) == {
        "files": {"tests/test_a.py": 3.0, "tests/test_b.py": 1.0},
        "tests": {"tests/test_a.py::test_one": 2.5, "tests/test_b.py::test_three": 1.0}}
    script = load_script(ROOT / "benchmarks" / "test_durations.py", monkeypatch)
    assert script.LISTED_S <= SLOW_S  # every test it would mark is listed


def test_test_fast_leaves_out_the_tests_listed_as_slow():
    tests = json.loads((ROOT / "tests" / "durations.json").read_text())["tests"]
    slow = [t for t, s in tests.items() if s >= SLOW_S and "[" not in t]
    assert slow, "durations.json lists no test over SLOW_S"
    file = slow[-1].split("::")[0]  # the quickest of them, in its file
    res = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-m",
                          "not slow", "-p", "no:cacheprovider", file],
                         capture_output=True, text=True, cwd=ROOT)
    assert res.returncode in (0, 5) and "deselected" in res.stdout, res.stdout + res.stderr
    kept = [line for line in res.stdout.splitlines() if "::" in line]
    assert slow[-1] not in kept
    assert all(tests.get(t, 0.0) < SLOW_S for t in kept)


def test_each_process_logs_its_cpu_time_at_exit_and_the_summary_sums_them_by_kind(tmp_path):
    """benchmarks/process_cpu: a process started with its folder on PYTHONPATH writes one line
    at exit, naming the test that started it; the summary adds them up by kind."""
    log = tmp_path / "cpu.jsonl"
    env = {**os.environ, "PYTHONPATH": str(ROOT / "benchmarks" / "process_cpu"),
           "PROCESS_CPU_LOG": str(log), "PYTEST_CURRENT_TEST": "tests/test_x.py::test_y (call)"}
    spin = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.2: pass"
    for _ in range(2):
        subprocess.run([sys.executable, "-c", spin], env=env, check=True)
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    assert len(lines) == 2 and all(x["cpu"] >= 0.2 and x["wall"] > 0 for x in lines)
    assert {x["test"] for x in lines} == {"tests/test_x.py::test_y (call)"}
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "process_cpu.py"), str(log)],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("2 processes, ")
    assert "   2  python -c (a test's script)" in res.stdout
