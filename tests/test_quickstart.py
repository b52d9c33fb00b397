"""The README's Quickstart, run as printed: each ``python -m lbo.<command>`` line of its code
block, in order, in a folder of its own.

Two lines are stood in for, each said where: ``python -m lbo.train experiment=robust`` (about
5 minutes) by the robust observer trained at smoke size once per test run (the
``robust_smoke`` fixture), whose run id takes the place of ``<run id>``; and the ``make``
lines, which other tests run (``make reproduce SCALE=smoke``: test_reproduce; ``make ui`` is a
server a person opens). The example log's path is the repository's.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pandas as pd
import pytest

from helpers import cli

REPO = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]


def quickstart_lines() -> list[str]:
    """The commands of the README's Quickstart code block, comments cut, in order."""
    text = (REPO / "README.md").read_text()
    section = text.split("## Quickstart\n", 1)[1].split("\n## ", 1)[0]
    block = section.split("```bash\n", 1)[1].split("```", 1)[0]
    return [line.split("#", 1)[0].strip() for line in block.splitlines()
            if line.strip() and not line.lstrip().startswith("#")]


def test_the_quickstart_has_the_commands_this_test_runs():
    lines = quickstart_lines()
    python = [line for line in lines if line.startswith("python -m lbo.")]
    assert [line.split()[2] for line in python] == [
        "lbo.observe", "lbo.train", "lbo.simulate", "lbo.observe"]
    assert "experiment=robust" in python[1]


def test_each_quickstart_command_runs_as_printed_and_prints_its_nrmse_beside_the_ekf(
        tmp_path, robust_smoke):
    run_id = robust_smoke["run_id"]
    env = {"MLFLOW_TRACKING_URI": robust_smoke["uri"]}
    said: list[str] = []
    for line in quickstart_lines():
        if not line.startswith("python -m lbo.") or " lbo.train " in f" {line} ":
            continue  # the make lines and the training: see the module's docstring
        words = shlex.split(line.replace("<run id>", run_id))
        args = [str(REPO / w) if w.startswith("examples/") else
                re.sub(r"=examples/", f"={REPO}/examples/", w) for w in words[3:]]
        res = cli(words[2], *args, env=env, cwd=tmp_path)
        assert res.returncode == 0, f"{line}\n{res.stderr[-3000:]}"
        said.append(res.stdout)
    first, simulated, robust = said
    assert "nrmse 1 (E_ref: the EKF on the same rows" in first
    assert (tmp_path / "estimates.png").stat().st_size > 20_000
    noisy = pd.read_csv(tmp_path / "noisy.csv")
    assert {"x", "y", "psi", "x_m", "V", "delta"} <= set(noisy.columns)
    assert "alpha 4" in simulated
    # the smoke observer is barely trained, so its number is not the README's: what is
    # checked is that the line a reader compares is printed, with the EKF beside it
    assert re.search(r"^nrmse \S+ \(E_ref: the EKF on the same rows", robust, re.M), robust
    assert re.search(r"^compare ekf: rmse x", robust, re.M), robust
    assert (tmp_path / "robust.png").stat().st_size > 20_000
