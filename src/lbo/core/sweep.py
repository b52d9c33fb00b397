"""The table a sweep ends with: every run's result side by side.

``python -m lbo.train -m model=cnn,lstm window=20,40,60,80`` prints each run's result as it
ends, eight tables apart. :class:`SweepTable`, a Hydra callback (``conf/hydra/default.yaml``),
reads each job's ``evaluation.csv`` from the sweep's folder once every job has returned (on
the machine that launched them, under any launcher) and prints one table: each learned
observer's NRMSE at alpha 1, 3 and 6 beside the EKF's and the oracle's, and its worst ratio
to the oracle. A sweep of another command, or one whose jobs wrote no evaluation, prints
nothing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

ALPHAS = (1.0, 3.0, 6.0)
"""The noise levels the table shows (those every run prints)."""
PEERS = ("ekf", "oracle")
"""The classical rows of an ``evaluation.csv`` shown once, beside the learned ones."""


def table(folder: str | Path) -> str:
    """The sweep in ``folder`` as a text table (one row per job's learned observer, then the
    peers of the first), or "" when no job there wrote an ``evaluation.csv``."""
    import numpy as np
    import pandas as pd

    files = sorted(Path(folder).glob("*/evaluation.csv"),
                   key=lambda p: (len(p.parent.name), p.parent.name))  # job 10 after job 9
    rows: list[tuple[str, list[float], float]] = []
    peers: list[tuple[str, list[float], float]] = []
    for path in files:
        df = pd.read_csv(path)
        oracle = df[df["observer"] == "oracle"].set_index("alpha")["nrmse"]
        for name, part in df.groupby("observer", sort=False):
            by = part.set_index("alpha")["nrmse"]
            cells = [float(by.get(a, np.nan)) for a in ALPHAS]
            both = by.index.intersection(oracle.index)
            both = both[(both >= 0.25) & (both <= 6)]
            worst = float((by[both] / oracle[both]).max()) if len(both) else float("nan")
            entry = (f"{name} (job {path.parent.name})", cells, worst)
            if name not in PEERS:
                rows.append(entry)
            elif all(p[0] != name for p in peers):
                peers.append((str(name), cells, worst))
    if not rows:
        return ""
    width = max(len(r[0]) for r in rows + peers)
    lines = [f"  {'observer':<{width}}  " + "  ".join(f"alpha {a:g}" for a in ALPHAS)
             + "  worst / oracle"]
    for name, cells, worst in rows + peers:
        lines.append(f"  {name:<{width}}  " + "  ".join(f"{c:7.3f}" for c in cells)
                     + f"  {worst:14.3f}")
    return "\n".join(lines)


class SweepTable(Callback):
    """Print :func:`table` of the sweep's folder when a multirun ends."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        text = table(str(config.hydra.sweep.dir))
        if text:
            print(f"the sweep's runs side by side (NRMSE, the EKF at alpha 1 is 1), from each "
                  f"job's evaluation.csv in {config.hydra.sweep.dir}:\n{text}", flush=True)
