"""The README's measured tables are rendered from tracked result files
(benchmarks/readme_tables.py): the README in the repository is current, a result changed
without its table (or a table edited by hand) is named in one line, a rebuild mends it, and a
result file its table cannot be rendered from is refused before anything is written."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from lbo.core.paths import REPO_ROOT

SCRIPT = REPO_ROOT / "benchmarks" / "readme_tables.py"
OBSERVERS = [f"{m}-N{n}" for m in ("cnn", "lstm") for n in (20, 40, 60, 80)] + [
    "filternet-N100", "ekf", "oracle", "adaptive", "ukf", "pcrb"]


def tables(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), "--root", str(root), *args],
                          capture_output=True, text=True, timeout=120)


def report(path: Path, observers: list[str] = OBSERVERS) -> Path:
    """A report's nrmse.csv: observer i's NRMSE at alpha a is (i + 1) * (a + 0.5) / 7."""
    rows = [(o, a, (i + 1) * (a + 0.5) / 7) for i, o in enumerate(observers)
            for a in np.arange(0.0, 6.25, 0.25)]
    pd.DataFrame(rows, columns=["observer", "alpha", "nrmse"]).to_csv(path, index=False)
    return path


def test_the_readme_in_the_repository_is_rendered_from_its_result_files():
    res = tables(REPO_ROOT, "--check")
    assert res.returncode == 0, res.stderr


def test_a_stale_table_is_named_and_a_rebuild_mends_it(tmp_path):
    (tmp_path / "docs" / "results").mkdir(parents=True)
    shutil.copy(REPO_ROOT / "docs" / "results" / "learned_cells.csv",
                tmp_path / "docs" / "results")
    (tmp_path / "README.md").write_text(
        "# x\n\n<!-- table: results -->\n| old |\n<!-- /table -->\n\ntext\n\n"
        "<!-- table: learned -->\n<!-- /table -->\n")
    res = tables(tmp_path, "--take", f"results={report(tmp_path / 'nrmse.csv')}")
    assert res.returncode == 0, res.stderr
    text = (tmp_path / "README.md").read_text()
    # observer i (1-based, in the table's column order) has NRMSE i * (alpha + 0.5) / 7
    assert ("| 3 | 0.500 | 1.00 | 1.50 | 2.00 | 2.50 | 3.00 | 3.50 | 4.00 | 4.50 | 5.00 | 5.50 "
            "| 6.00 | 6.50 | 7.00 |\n| 6 | 0.929 | 1.86 | 2.79 | 3.71 | 4.64 | 5.57 | 6.50 | 7.43 "
            "| 8.36 | 9.29 | 10.2 | 11.1 | 12.1 | 13.0 |\n<!-- /table -->\n\ntext\n") in text
    assert "| Split-KalmanNet, trained carried (`tbptt=100`) | not run |" in text
    assert tables(tmp_path, "--check").returncode == 0
    assert tables(tmp_path).returncode == 0 and (tmp_path / "README.md").read_text() == text

    cells = pd.read_csv(tmp_path / "docs" / "results" / "learned_cells.csv")
    cells.loc[0, "ratio_3"] = 9.87  # a re-measured result, its table not rebuilt
    cells.to_csv(tmp_path / "docs" / "results" / "learned_cells.csv", index=False)
    res = tables(tmp_path, "--check")
    assert res.returncode == 1
    assert res.stderr.splitlines() == [
        "error: README.md: tables learned differ from their result files; run make "
        "readme-tables"]
    assert tables(tmp_path).returncode == 0
    assert "9.87" in (tmp_path / "README.md").read_text()
    assert tables(tmp_path, "--check").returncode == 0


def test_a_result_file_its_table_cannot_be_rendered_from_is_refused_before_writing(tmp_path):
    (tmp_path / "README.md").write_text("<!-- table: results -->\n<!-- /table -->\n")
    bad = report(tmp_path / "nrmse.csv", OBSERVERS[:-1])  # no PCRB
    res = tables(tmp_path, "--take", f"results={bad}")
    assert res.returncode == 1
    assert res.stderr.splitlines() == [
        "error: results: the report lacks observers ['pcrb'] or alphas []; expected make "
        "reproduce's report (nrmse.csv)"]
    assert not (tmp_path / "docs").exists()
    res = tables(tmp_path)
    assert res.stderr.splitlines() == [
        "error: README table 'results': docs/results/quick_nrmse.csv is missing; measure it "
        "and give it with --take results=<file>"]
    assert tables(tmp_path, "--take", "nothing=x.csv").stderr.splitlines() == [
        "error: --take nothing: expected one of ['learned', 'results']"]
