"""Receiver-study runs side by side: the learned gyro EKF's row of each run against the first
run's (lbo's measure: the quadratic mean over x, y and psi of the RMSE ratios), per alpha, and
the defaults' row against it.

    python -m lbo.receiver_study output_dir=a observers=[ekf,gyro]
    python -m lbo.receiver_study output_dir=b observers=[ekf,gyro] learn.objective=innovations
    python benchmarks/learned_vs_supervised.py a/results.csv b/results.csv
"""

import sys

import numpy as np
import pandas as pd

from lbo.receiver_study import LEARNED
from lbo.scoring.receiver import RMSE

DEFAULTS = "gyro, receiver's accuracy and velocity"


def row(table: pd.DataFrame, alpha: float, estimator: str) -> np.ndarray:
    return table[(table["alpha"] == alpha) & (table["estimator"] == estimator)][
        list(RMSE)].to_numpy(float)[0]


base = pd.read_csv(sys.argv[1])
for path in sys.argv[2:]:
    other = pd.read_csv(path)
    for alpha in sorted(base["alpha"].unique()):
        ref = row(base, alpha, LEARNED)
        learned = float(np.sqrt(np.mean((row(other, alpha, LEARNED) / ref) ** 2)))
        defaults = float(np.sqrt(np.mean((row(other, alpha, DEFAULTS) / ref) ** 2)))
        print(f"{path}: alpha {alpha:g}: learned {learned:.3f}, defaults {defaults:.3f} "
              f"times the first run's learned row")
