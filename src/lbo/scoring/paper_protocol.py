"""The paper's protocol beside ours: which EKF setting would give the paper's published EKF
errors, how close a learned variant comes to its Tables I and II, and the ablation's table.

Frames and arrays in, frames out; :mod:`lbo.ablation` trains the variants and calls these.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import pandas as pd

from lbo.core.errors import LboError
from lbo.filters.kalman import ekf_batch
from lbo.scoring.metrics import nrmse, pooled_rmse
from lbo.scoring.report import PAPER_RMSE, VARIABLES, crossover
from lbo.sim.noise import Noise
from lbo.sim.schema import Trajectories
from lbo.sim.vehicle import Vehicle

EKF_FIT_GRID = ((1.0, 1.5, 2.0, 2.5, 3.0), (1.0, 1.5, 2.0, 3.0))
"""Factors on the noise preset's process sigmas (position, heading) that the fit tries; R
stays at alpha = 1, as in the paper's EKF."""
FIT_TOLERANCE = 0.15
"""An EKF setting reproduces the paper's EKF when every RMSE at alpha 1 and 6 is within this."""
SHAPE_TOLERANCE = 1.5
"""A learned variant reproduces the paper's Table I or II when every RMSE is within this factor."""
PAPER_FIT = "ekf_paper_fit"
"""Name of the EKF setting closest to the paper's EKF in a score table."""
ALPHAS = (1.0, 6.0)


def paper_rmse(key: str) -> np.ndarray:
    """(2, 3) the paper's RMSE of ``key`` (ekf, cnn, lstm) at alpha 1 and 6, psi in rad."""
    return np.array([PAPER_RMSE[a][key] for a in ALPHAS])


def scaled_q(noise: Noise, position: float, heading: float) -> np.ndarray:
    """(3, 3) the preset's process covariance with its sigmas times (position, position,
    heading)."""
    sigma = np.asarray(noise.process_sigma) * np.array([position, position, heading])
    return np.diag(sigma**2)


def run_scaled_ekf(arr: Trajectories, vehicle: Vehicle, noise: Noise,
                   position: float, heading: float) -> np.ndarray:
    """Estimates (G, T, 3) of the EKF with R at alpha = 1 and Q scaled (:func:`scaled_q`)."""
    R = np.diag(np.square(noise.meas(1.0)))
    return ekf_batch(arr.m, arr.u, vehicle, scaled_q(noise, position, heading), R).mean


def fit_paper_ekf(arr: Trajectories, vehicle: Vehicle, noise: Noise,
                  grid: Sequence[Sequence[float]] = EKF_FIT_GRID,
                  target: np.ndarray | None = None) -> pd.DataFrame:
    """Score the EKF at every (position, heading) factor of ``grid`` at alpha 1 and 6.

    Parameters
    ----------
    arr : the padded test arrays of :func:`lbo.scoring.grid.load_test` (alpha 1 and 6 needed).
    target : (2, 3) RMSE x, y, psi (rad) at alpha 1 and 6 to fit; None: the paper's EKF.

    Returns
    -------
    One row per setting, closest first: ``q_position, q_heading``, the RMSE
    ``{x,y,psi}_{1,6}`` (psi in mrad), the growth ``growth_{x,y,psi}`` (RMSE at 6 over 1) and
    ``deviation``, the largest ``|ours / paper - 1|`` over the six numbers.
    """
    sets = {a: arr.take(np.isclose(arr.alpha, a)) for a in ALPHAS}
    for a, s in sets.items():
        if not len(s.alpha):
            raise LboError(f"the paper's EKF is fitted at alpha 1 and 6; the test set has no "
                           f"trajectory at alpha = {a:g}")
    paper = paper_rmse("ekf") if target is None else np.asarray(target, dtype=float)
    rows = []
    for position, heading in itertools.product(*grid):
        got = np.array([pooled_rmse(run_scaled_ekf(s, vehicle, noise, position, heading),
                                    s.z, s.mask) for s in sets.values()])
        row = {"q_position": position, "q_heading": heading}
        for i, a in enumerate(ALPHAS):
            for j, (var, _, scale) in enumerate(VARIABLES):
                row[f"{var}_{a:g}"] = got[i, j] * scale
        for j, (var, _, _) in enumerate(VARIABLES):
            row[f"growth_{var}"] = got[1, j] / got[0, j]
        row["deviation"] = float(np.abs(got / paper - 1).max())
        rows.append(row)
    return pd.DataFrame(rows).sort_values("deviation", kind="stable", ignore_index=True)


def paper_distance(table: pd.DataFrame, observer: str, model: str) -> dict[str, float]:
    """How far ``observer``'s RMSE is from the paper's ``model`` (cnn or lstm): the largest
    factor either way over x, y and psi, at alpha 1 (``alpha1``) and at alpha 6 (``alpha6``).
    1 is exact; :data:`SHAPE_TOLERANCE` is the bar. NaN where ``table`` lacks that alpha."""
    paper = paper_rmse(model)
    out = {}
    for i, a in enumerate(ALPHAS):
        row = table[(table["observer"] == observer) & np.isclose(table["alpha"], a)]
        if row.empty:
            out[f"alpha{a:g}"] = float("nan")
            continue
        ours = row[["rmse_x", "rmse_y", "rmse_psi"]].to_numpy()[0]
        ratio = ours / paper[i]
        out[f"alpha{a:g}"] = float(np.max(np.maximum(ratio, 1 / ratio)))
    return out


def paper_rows(ref: np.ndarray) -> pd.DataFrame:
    """The paper's EKF, CNN and LSTM at alpha 1 and 6 as score rows (``paper_ekf`` ...), their
    NRMSE against ``ref`` (3,)."""
    rows = []
    for key in ("ekf", "cnn", "lstm"):
        for a in ALPHAS:
            r = np.array(PAPER_RMSE[a][key])
            rows.append({"observer": f"paper_{key}", "alpha": a, "rmse_x": r[0],
                         "rmse_y": r[1], "rmse_psi": r[2], "nrmse": float(nrmse(r, ref))})
    return pd.DataFrame(rows)


def mean_over_seeds(tables: Sequence[pd.DataFrame], observer: str,
                    label: str) -> pd.DataFrame:
    """Score rows of ``label``: the RMSE of ``observer`` averaged over the seeds' tables per
    alpha, the NRMSE recomputed from them is replaced by the seeds' mean NRMSE, and
    ``nrmse_min, nrmse_max`` give the seeds' spread."""
    rows = pd.concat([t[t["observer"] == observer] for t in tables], ignore_index=True)
    cols = ["rmse_x", "rmse_y", "rmse_psi", "nrmse"]
    g = rows.groupby("alpha")
    out = g[cols].mean()
    out["nrmse_min"], out["nrmse_max"] = g["nrmse"].min(), g["nrmse"].max()
    out["seeds"] = g.size()
    return out.reset_index().assign(observer=label)


def variant_summary(table: pd.DataFrame, variants: pd.DataFrame) -> pd.DataFrame:
    """The ablation's table: one row per variant of ``variants`` (columns ``label, model``
    and the factors), with the RMSE at alpha 1, 3 and 6 (psi in mrad) of its seed-mean rows in
    ``table``, the NRMSE growth from alpha 1 to 6, the seeds' NRMSE spread at alpha 6, the
    crossovers with our EKF and with :data:`PAPER_FIT` (NaN: never on the grid), and the
    distance to the paper's Tables I and II (:func:`paper_distance`)."""
    rows = []
    for v in variants.to_dict("records"):
        t = table[table["observer"] == v["label"]].set_index("alpha")
        row = dict(v)
        for a in (1.0, 3.0, 6.0):
            for var, _, scale in VARIABLES:
                row[f"{var}_{a:g}"] = t["rmse_" + var].get(a, np.nan) * scale
        row["growth"] = t["nrmse"].get(6.0, np.nan) / t["nrmse"].get(1.0, np.nan)
        row["seeds"] = int(t["seeds"].max()) if "seeds" in t else 1
        if "nrmse_max" in t and 6.0 in t.index:
            row["spread_6"] = (t.loc[6.0, "nrmse_max"] - t.loc[6.0, "nrmse_min"]) / t.loc[6.0,
                                                                                        "nrmse"]
        for peer in ("ekf", PAPER_FIT):
            cross = crossover(table, v["label"], peer)
            row[f"crossover_{peer}"] = np.nan if cross is None else cross
        row.update({f"paper_{k}": d for k, d in
                    paper_distance(table, v["label"], v["model"]).items()})
        rows.append(row)
    return pd.DataFrame(rows)
