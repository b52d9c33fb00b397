"""Scores on a user's test logs (``data=logs``): the test files play the role of the test
grid.

Every observer is scored on the same rows (each test segment from step ``data.run_in`` on):
the RMSE per variable pooled over every test file (``file = all``) and per file, the NRMSE
normalised by the EKF on the same files (so the EKF's pooled NRMSE is 1), and each observer's
NRMSE over every classical peer's on the same rows (``ratio_to_<peer>``). A log has no known
noise level, so the peers are the EKF at the noise preset's R (alpha=1), the adaptive EKF that
learns R, and the UKF; the oracle EKF (told alpha) cannot be run. The ``alpha`` column is the
noise level the reference measures in each file, which no observer is told.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import cast

import numpy as np
import pandas as pd

from lbo.core.errors import LboError
from lbo.filters.classical import LOG_PEERS, first_fixes
from lbo.scoring.metrics import nrmse, pooled_rmse
from lbo.sim import schema
from lbo.sim.columns import SCORED_SET
from lbo.sim.noise import Noise
from lbo.sim.schema import Trajectories
from lbo.sim.vehicle import Vehicle

ALL = "all"
NOTE = ("on logs the noise level is unknown, so there is no oracle EKF: the peers are the EKF "
        "at the noise preset's R (alpha=1), the adaptive EKF (learns R) and the UKF; NRMSE is "
        "normalised by the EKF on the same test files")


def load(folder: str | Path) -> Trajectories:
    """The test logs of a ``data=logs`` folder as padded arrays (:func:`lbo.sim.schema.to_arrays`)
    with ``file`` (G,), the index of each segment's log; each is scored from its first fix on
    (a log may start between fixes), and segments with nothing to score (shorter than
    ``data.run_in``) are left out."""
    df = schema.read_set(Path(folder) / "test.parquet", SCORED_SET, missing_fixes=True)
    arr = schema.to_arrays(df)
    # a segment may start between fixes: every observer is scored from its first fix on
    arr = replace(arr, file=df.groupby("traj")["file"].first().loc[arr.traj].to_numpy(),
                  mask=arr.mask & (np.arange(arr.m.shape[1]) >= first_fixes(arr.m)[:, None]))
    return arr.take(cast(np.ndarray, arr.mask.any(axis=1)))  # (G,): the mask is (G, T)


def peer_estimates(arr: Trajectories, vehicle: Vehicle, noise: Noise,
                   peers: Sequence[str] = LOG_PEERS) -> dict[str, np.ndarray]:
    """Estimates (G, T, 3) of each classical peer on the test arrays, never told alpha."""
    from lbo.filters.classical import estimate

    for name in peers:
        if name not in LOG_PEERS:
            raise LboError(f"observers: {name!r} cannot score logs ({NOTE}); expected names "
                           f"from {list(LOG_PEERS)}")
    return {name: estimate(name, arr.m, arr.u, vehicle, noise).mean for name in peers}


def table(estimates: Mapping[str, np.ndarray], arr: Trajectories,
          files: Sequence[str]) -> pd.DataFrame:
    """Rows ``observer, file, alpha, rmse_x, rmse_y, rmse_psi, nrmse, ratio_to_<peer>...``.

    Parameters
    ----------
    estimates : observer name -> (G, T, 3) estimates; must hold ``ekf``, the reference.
    arr : the test arrays of :func:`load`.
    files : the test logs' names, indexed by ``arr.file``.
    """
    if "ekf" not in estimates:
        raise LboError("scoring logs needs the EKF's estimates: the NRMSE is normalised by it")
    z, mask = arr.z, arr.mask
    groups = [(ALL, np.ones(len(z), bool))] + [
        (str(f), arr.file == i) for i, f in enumerate(files) if (arr.file == i).any()]
    levels = {str(f): float(arr.alpha[arr.file == i][0])
              for i, f in enumerate(files) if (arr.file == i).any()}
    ref = pooled_rmse(estimates["ekf"], z, mask)
    rows = []
    for name, est in estimates.items():
        for label, sel in groups:
            e = pooled_rmse(est[sel], z[sel], mask[sel])
            level = levels.get(label, float(np.mean(list(levels.values()))))
            rows.append({"observer": name, "file": label, "alpha": level, "rmse_x": e[0],
                         "rmse_y": e[1], "rmse_psi": e[2], "nrmse": nrmse(e, ref)})
    out = pd.DataFrame(rows)
    piv = out.pivot(index="file", columns="observer", values="nrmse")
    for peer in (p for p in LOG_PEERS if p in estimates):
        out[f"ratio_to_{peer}"] = out["nrmse"].to_numpy() / piv.loc[out["file"], peer].to_numpy()
    return out


def metrics(scores: pd.DataFrame, observer: str) -> dict[str, float]:
    """The pooled scores of ``observer`` as MLflow metrics: ``test_nrmse``,
    ``test_rmse_{x,y,psi}`` and ``ratio_to_<peer>``; across two test logs or more, also
    ``test_drives_vs_ekf_mean`` and ``_worst`` (:func:`drive_metrics`)."""
    row = scores[(scores["observer"] == observer) & (scores["file"] == ALL)].iloc[0]
    out = {"test_nrmse": float(row["nrmse"])}
    out.update({f"test_rmse_{v}": float(row[f"rmse_{v}"]) for v in ("x", "y", "psi")})
    out.update({c: float(row[c]) for c in scores.columns if c.startswith("ratio_to_")})
    return out | drive_metrics(scores, observer, "test_")


def drive_metrics(scores: pd.DataFrame, observer: str, prefix: str) -> dict[str, float]:
    """``<prefix>drives_vs_ekf_mean`` and ``_worst``: the mean and the worst over the test
    logs of ``observer``'s ratio to the EKF on each (:func:`across`); none with one log."""
    if scores["file"].nunique() <= 2:  # the pooled row and one log
        return {}
    wide = across(scores)
    row = wide[wide["estimator"] == observer].iloc[0]
    return {f"{prefix}drives_vs_ekf_mean": float(row["mean"]),
            f"{prefix}drives_vs_ekf_worst": float(row["worst"])}


def across(scores: pd.DataFrame) -> pd.DataFrame:
    """Every observer's ``ratio_to_ekf`` on each test log (a drive), their mean and the worst
    (:func:`lbo.scoring.drives.summary`: one row per observer, a column per log named by its
    file's name): a gain pooled over the logs may hide a log it makes worse."""
    from lbo.scoring.drives import summary

    per_log = scores[scores["file"] != ALL]
    files = list(dict.fromkeys(per_log["file"]))
    short = {f: Path(f).name for f in files}
    names = short if len(set(short.values())) == len(files) else {f: f for f in files}
    return summary(pd.DataFrame({"drive": [names[f] for f in per_log["file"]],
                                 "estimator": per_log["observer"],
                                 "vs_ekf": per_log["ratio_to_ekf"]}))


def figure(scores: pd.DataFrame, title: str = ""):
    """NRMSE per test file (and pooled) for every observer, as grouped bars."""
    import matplotlib.pyplot as plt

    from lbo.core.plots import STYLES

    piv = scores.pivot(index="file", columns="observer", values="nrmse")
    files = [ALL] + [f for f in dict.fromkeys(scores["file"]) if f != ALL]
    names = list(dict.fromkeys(scores["observer"]))
    piv = piv.loc[files, names]
    fig, ax = plt.subplots(figsize=(max(6.4, 0.9 * len(files) + 2), 4.2))
    width = 0.8 / len(names)
    palette = iter(["tab:blue", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:cyan"])
    x = np.arange(len(files))
    for i, name in enumerate(names):
        color = (STYLES.get(name) or {}).get("color") or next(palette)
        ax.bar(x + (i - (len(names) - 1) / 2) * width, piv[name].to_numpy(), width,
               label=name, color=color)
    values = piv.to_numpy()
    if np.nanmax(values) > 5 * np.nanmin(values):  # a diverged peer would flatten the others
        ax.set_yscale("log")
    ax.axhline(1.0, color="0.6", lw=0.8, ls=":")
    ax.set_xticks(x, [Path(f).name for f in files], rotation=30, ha="right", fontsize=8)
    ax.set(ylabel="NRMSE (EKF on the same files = 1)", title=title)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def printable(scores: pd.DataFrame) -> str:
    """The pooled rows as a text table: RMSE per variable (m, m, mrad), NRMSE and ratios."""
    pooled = scores[scores["file"] == ALL].set_index("observer")
    cols = ["rmse_x", "rmse_y", "rmse_psi", "nrmse",
            *[c for c in scores.columns if c.startswith("ratio_to_")]]
    shown = pooled[cols].copy()
    shown["rmse_psi"] *= 1e3
    shown = shown.rename(columns={"rmse_x": "x (m)", "rmse_y": "y (m)", "rmse_psi": "psi (mrad)"})
    with pd.option_context("display.width", 140, "display.precision", 4):
        return shown.to_string()
