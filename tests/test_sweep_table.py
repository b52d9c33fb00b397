"""The table a sweep ends with (lbo.core.sweep, issue 73): each job's learned observer beside
the peers, in job order, read from the jobs' evaluation.csv."""

from __future__ import annotations

import pandas as pd

from lbo.core.sweep import table

ALPHAS = (0.0, 0.25, 1.0, 3.0, 6.0, 7.0)


def _evaluation(folder, job: str, name: str, scale: float) -> None:
    rows = []
    for a in ALPHAS:
        oracle = 1.0 + a / 3
        rows += [{"observer": name, "alpha": a, "nrmse": scale * oracle},
                 {"observer": "ekf", "alpha": a, "nrmse": 1.0 + a / 2},
                 {"observer": "oracle", "alpha": a, "nrmse": oracle}]
    (folder / job).mkdir()
    pd.DataFrame(rows).to_csv(folder / job / "evaluation.csv", index=False)


def test_each_job_in_order_beside_the_peers_once(tmp_path):
    for job, scale in (("10", 1.5), ("9", 1.2), ("0", 1.1)):
        _evaluation(tmp_path, job, f"cnn-{job}", scale)
    (tmp_path / "11").mkdir()  # a job that wrote no evaluation (a refused one)
    lines = table(tmp_path).splitlines()
    assert lines[0].split() == ["observer", "alpha", "1", "alpha", "3", "alpha", "6", "worst",
                                "/", "oracle"]
    names = [line.split()[0] for line in lines[1:]]
    assert names == ["cnn-0", "cnn-9", "cnn-10", "ekf", "oracle"]
    cnn9 = lines[2].split()
    # NRMSE at alpha 1, 3, 6, then the worst ratio to the oracle over alpha 0.25-6
    assert [float(c) for c in cnn9[-4:]] == [1.6, 2.4, 3.6, 1.2]
    ekf = lines[4].split()
    assert float(ekf[-1]) == round(max((1 + a / 2) / (1 + a / 3)
                                       for a in ALPHAS if 0.25 <= a <= 6), 3)


def test_a_sweep_without_evaluations_prints_nothing(tmp_path):
    assert table(tmp_path) == ""
    (tmp_path / "0").mkdir()
    assert table(tmp_path) == ""
