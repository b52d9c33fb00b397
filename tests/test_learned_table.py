"""The comparison table of every learned observer (benchmarks/learned_table.py), at smoke
scale: each cell is one lbo.train run under the table's budget, read back from its
evaluation.csv, its checkpoint and its MLflow run; a finished cell is read, not trained
again; a cell that is not in the table is refused in one line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from helpers.scripts import load_script, run_script
from lbo.core.paths import REPO_ROOT

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]
SCRIPT = REPO_ROOT / "benchmarks" / "learned_table.py"


def _smoke(smoke_data: Path) -> list[str]:
    return ["data=smoke", f"data.root={smoke_data.parent}",
            "trainer.max_epochs=1", "++trainer.limit_train_batches=2",
            "++trainer.limit_val_batches=2", "window=20"]


def table(tmp_path: Path, smoke_data: Path, *args: str) -> subprocess.CompletedProcess:
    """``python benchmarks/learned_table.py --out <tmp>/table <args> -- <smoke>`` in a process
    of its own (its exit status and stderr as a user sees them)."""
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    return subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "table"), *args,
                           "--", *_smoke(smoke_data)], capture_output=True, text=True, env=env,
                          timeout=900, cwd=tmp_path)


def table_here(tmp_path: Path, smoke_data: Path, monkeypatch, capsys, *args: str) -> str:
    """The same command's ``main`` in this process, with the same arguments, environment and
    folder (each cell is still its own ``python -m lbo.train`` process, as the script starts
    it): what it printed."""
    with monkeypatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
        mp.chdir(tmp_path)
        return run_script(SCRIPT, ["--out", str(tmp_path / "table"), *args, "--",
                                   *_smoke(smoke_data)], monkeypatch, capsys)


def test_each_cell_is_a_run_read_back_and_a_finished_one_is_not_trained_again(
        tmp_path, smoke_data, monkeypatch, capsys):
    cells = "paper/cnn,robust/split_kalmannet"
    printed = table_here(tmp_path, smoke_data, monkeypatch, capsys, "--cells", cells)
    rows = pd.read_csv(tmp_path / "table" / "cells.csv")
    assert list(rows["observer"]) == ["cnn", "split_kalmannet"]
    for row in rows.itertuples():
        ev = pd.read_csv(Path(row.folder) / "evaluation.csv")
        nr = ev.pivot(index="alpha", columns="observer", values="nrmse")
        for a in (1, 3, 6):
            assert getattr(row, f"nrmse_{a}") == pytest.approx(nr.loc[a, row.run])
            assert getattr(row, f"ratio_{a}") == pytest.approx(
                nr.loc[a, row.run] / nr.loc[a, "oracle"])
            assert getattr(row, f"ekf_ratio_{a}") == pytest.approx(
                nr.loc[a, "ekf"] / nr.loc[a, "oracle"])
        assert row.parameters > 100 and row.seconds > 0
    md = (tmp_path / "table" / "table.md").read_text()
    assert "| paper | CNN (N=80) |" in md and "| robust | Split-KalmanNet |" in md
    assert md.count("| EKF, R at alpha = 1 |") == 2  # a reference line per data set
    assert "train_noise=paper" in printed and "model=split_kalmannet" in printed
    # again: both cells are read from their folders, none trained
    again = table_here(tmp_path, smoke_data, monkeypatch, capsys, "--cells", cells)
    assert "model=cnn" not in again and "train_noise" not in again
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "table" / "cells.csv"), rows)


def test_a_cell_not_in_the_table_is_refused_in_one_line(tmp_path, smoke_data):
    res = table(tmp_path, smoke_data, "--cells", "paper/cnn,paper/gru")
    assert res.returncode == 1
    assert res.stderr.strip().splitlines() == [
        "error: --cells: unknown cell(s) paper/gru; expected <data set>/<observer> of "
        + ", ".join(f"{d}/{o}" for d in ("paper", "robust", "dynamic") for o in (
            "cnn", "lstm", "robust", "slips", "kalmannet", "split_kalmannet",
            "split_kalmannet_carried"))]
    assert not (tmp_path / "table").exists()


def test_a_cell_that_sets_a_budget_setting_keeps_its_own(monkeypatch):
    """Split-KalmanNet trained carried sets its batch of sequences: the budget's batch size
    is left out (Hydra refuses a key given twice), the rest of the budget kept."""
    module = load_script(SCRIPT, monkeypatch)
    (carried,) = module.cells("robust/split_kalmannet_carried", Path("out"), {})
    assert [o for o in carried.overrides if o.startswith("batch_size=")] == ["batch_size=100"]
    assert "tbptt=100" in carried.overrides and "trainer.max_epochs=4" in carried.overrides
    (plain,) = module.cells("robust/split_kalmannet", Path("out"), {})
    assert "batch_size=256" in plain.overrides
