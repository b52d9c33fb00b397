"""data=logs: every rule a log or a setting breaks is one line, before any run opens, and
nothing is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers import cli, compose_cfg
from lbo.core.errors import LboError

COLUMNS = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]


@pytest.fixture(scope="module")
def good(smoke_data, tmp_path_factory) -> Path:
    """Two training logs, one validation and one test log from the smoke test set."""
    root = tmp_path_factory.mktemp("good")
    test = pd.read_parquet(smoke_data / "test.parquet")
    parts = {(0, 0.0): "train/a", (1, 0.0): "train/b", (0, 1.0): "val/a", (1, 1.0): "test/a"}
    for (traj, alpha), name in parts.items():
        log = test[(test["traj"] == traj) & (test["alpha"] == alpha)].sort_values("k")[COLUMNS]
        (root / name).parent.mkdir(exist_ok=True)
        log.to_csv(root / f"{name}.csv", index=False)
    return root


def _set(df: pd.DataFrame, row: int, column: str, value) -> pd.DataFrame:
    d = df.copy()
    d.loc[d.index[row], column] = value
    return d


def _swap(df: pd.DataFrame) -> pd.DataFrame:
    d = df.copy()
    d.iloc[[10, 11]] = d.iloc[[11, 10]].to_numpy()
    return d


BAD_LOGS = {  # case: (the bad train/a.csv from the good one, what the message must say)
    "no_truth": (lambda d: d.drop(columns=["psi"]), "missing true-state column psi"),
    "nan_truth": (lambda d: _set(d, 5, "x", np.nan), "column 'x' has NaN or inf (first at row 5)"),
    "no_input": (lambda d: d.drop(columns=["V"]), "missing column V"),
    "nan_input": (lambda d: _set(d, 7, "V", np.nan), "column 'V' has NaN or inf (first at row 7)"),
    "degrees": (lambda d: d.assign(psi_m=np.degrees(d["psi_m"]) + 400),
                "column 'psi_m' looks like degrees"),
    "kmh": (lambda d: _set(d, 3, "V", 150.0), "row 3: V=150 m/s is beyond 100 m/s"),
    "unsorted": (_swap, "column 't' is not strictly increasing (row 11"),
    "milliseconds": (lambda d: d.assign(t=d["t"] * 1000), "column 't' looks like milliseconds"),
    "period": (lambda d: d.iloc[::2], "pass data.resample=true"),
    # the learned observers train on full fixes: a position without a heading is refused
    "no_heading": (lambda d: _set(d, 4, "psi_m", np.nan),
                   "row 4 has a position without a heading (psi_m empty)"),
    "steering": (lambda d: _set(d, 6, "delta", 1.5), "row 6: delta=1.5 rad is beyond"),
}


def _cfg(root: Path, tmp: Path, *overrides: str):
    return compose_cfg("train", ["experiment=smoke", "data=logs", f"data.train=[{root}/train]",
                                 f"data.val=[{root}/val]", f"data.test=[{root}/test]",
                                 "data.run_in=100", f"data.root={tmp}/data",
                                 f"output_dir={tmp}/out", *overrides])


def _refused(cfg, tmp: Path, uri: str, text: str) -> str:
    """Train ``cfg``: it must raise one line holding ``text``, open no MLflow run and write
    no data set."""
    import mlflow

    from lbo.train import train

    with pytest.raises(LboError) as e:
        train(cfg)
    message = str(e.value)
    assert text in message and "\n" not in message, message
    if Path(uri.removeprefix("sqlite:///")).exists():
        client = mlflow.MlflowClient(uri)
        ids = [x.experiment_id for x in client.search_experiments()]
        assert not ids or not client.search_runs(ids)
    assert not list((tmp / "data").glob("logs-*/*.parquet"))
    return message


@pytest.mark.parametrize("case", sorted(BAD_LOGS))
def test_a_bad_log_is_one_line_before_any_run(good, tmp_path, tracking, case):
    make, text = BAD_LOGS[case]
    root = tmp_path / "logs"
    for p in good.rglob("*.csv"):
        (root / p.parent.name).mkdir(parents=True, exist_ok=True)
        (root / p.parent.name / p.name).write_bytes(p.read_bytes())
    make(pd.read_csv(good / "train" / "a.csv")).to_csv(root / "train" / "a.csv", index=False)
    message = _refused(_cfg(root, tmp_path), tmp_path, tracking, text)
    assert "train/a.csv" in message  # names the file


BAD_SETTINGS = {
    "glob_nothing": (["data.train=[nowhere/*.csv]"], "data.train: no file matches"),
    "empty_list": (["data.val=[]"], "data.val must be a list of log files"),
    "missing_file": (["data.test=[nowhere.csv]"], "data.test: log not found: nowhere.csv"),
    "in_two_sets": (["data.test=[{root}/train/a.csv]"], "the sets are split by file"),
    "not_a_log": (["data.train=[{root}/notes.txt]"], "is not a .csv or .parquet log"),
    "run_in": (["data.run_in=5000"], "no segment is longer than data.run_in=5000"),
    "run_in_zero": (["data.run_in=0"], "data.run_in must be an integer >= 1"),
    "max_gap": (["data.max_gap=-1"], "data.max_gap must be a time in seconds > 0"),
    "resample": (["data.resample=maybe"], "data.resample must be true or false"),
    "init_from": (["init_from=nowhere.ckpt"], "init_from: observer: checkpoint not found"),
}


@pytest.mark.parametrize("case", sorted(BAD_SETTINGS))
def test_a_bad_setting_is_one_line_before_any_run(good, tmp_path, tracking, case):
    overrides, text = BAD_SETTINGS[case]
    (good / "notes.txt").write_text("not a log")
    cfg = _cfg(good, tmp_path, *(o.format(root=good) for o in overrides))
    _refused(cfg, tmp_path, tracking, text)


def test_an_unreadable_log_is_one_line(good, tmp_path, tracking):
    root = tmp_path / "logs"
    (root / "train").mkdir(parents=True)
    (root / "train" / "a.csv").write_bytes(b"\x00\xff\x10garbage\n\x00\x01")
    (root / "train" / "b.parquet").write_bytes(b"PAR1 not really")
    cfg = _cfg(good, tmp_path, f"data.train=[{root}/train/b.parquet]")
    _refused(cfg, tmp_path, tracking, "cannot read it as parquet")


def test_evaluate_refuses_a_bad_test_log_and_writes_nothing(good, tmp_path):
    bad = tmp_path / "bad.csv"
    pd.read_csv(good / "test" / "a.csv").drop(columns=["y"]).to_csv(bad, index=False)
    res = cli("lbo.evaluate", "data=logs", f"data.test=[{bad}]", "data.run_in=100",
              f"data.root={tmp_path}/data", f"hydra.run.dir={tmp_path}/out", cwd=tmp_path)
    assert res.returncode != 0
    lines = [ln for ln in res.stderr.splitlines() if "missing true-state column y" in ln]
    assert len(lines) == 1 and "bad.csv" in lines[0], res.stderr[-2000:]
    assert not list(tmp_path.rglob("evaluation.csv"))
