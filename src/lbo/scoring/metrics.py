"""Error metrics of the paper (section IV-A): arrays in, numbers out.

Heading errors are always wrapped to (-pi, pi] before squaring, so an estimate of
``psi + 2 pi - 0.01`` counts as an error of 0.01 rad whatever branch either side uses.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError

PAPER_REFERENCE = (0.24, 0.23, 4.1e-3)
"""E_ref of the paper: RMSE of its EKF at alpha=1 for x (m), y (m), psi (rad)."""

SCORE_COLUMNS = ["observer", "alpha", "rmse_x", "rmse_y", "rmse_psi", "nrmse"]


def _squared_errors(est: np.ndarray, truth: np.ndarray,
                    mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Masked squared errors (..., T, 3) (zero where unscored) and the mask (..., T)."""
    est = np.asarray(est, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if est.shape != truth.shape or est.ndim < 2 or est.shape[-1] != 3:
        raise LboError(f"est and truth must both be (..., T, 3) [x, y, psi], "
                       f"got {est.shape} and {truth.shape}")
    err = est - truth
    err[..., 2] = wrap_angle(err[..., 2])
    if mask is None:
        mask = np.ones(est.shape[:-1], dtype=bool)
    else:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != est.shape[:-1]:
            raise LboError(f"mask must be {est.shape[:-1]} (est without its last axis), "
                           f"got {mask.shape}")
    # where, not multiply: unscored steps may hold NaN (e.g. before a window fills)
    return np.where(mask[..., None], err**2, 0.0), mask


def rmse(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Root mean square error per variable over the scored steps.

    Parameters
    ----------
    est, truth : (..., T, 3) ``[x, y, psi]``; psi errors are wrapped.
    mask : (..., T) bool, True where a step is scored; None scores every step.

    Returns
    -------
    (..., 3) RMSE of x (m), y (m), psi (rad); NaN where nothing is scored.
    """
    sq, mask = _squared_errors(est, truth, mask)
    count = mask.sum(axis=-1)[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(sq.sum(axis=-2) / count)


def pooled_rmse(est: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3,) RMSE over every masked step of every trajectory together: est, truth (G, T, 3),
    mask (G, T)."""
    return rmse(est.reshape(1, -1, 3), truth.reshape(1, -1, 3), mask.reshape(1, -1))[0]


def nrmse(rmse_xyz: np.ndarray, ref: ArrayLike = PAPER_REFERENCE) -> float | np.ndarray:
    """Normalised RMSE ``sqrt(sum_i E_i^2 / (3 E_ref,i^2))`` (section IV-A); 1 for the reference.

    Parameters
    ----------
    rmse_xyz : (..., 3) RMSE of x, y, psi.
    ref : (3,) E_ref, by default the paper's :data:`PAPER_REFERENCE`.

    Returns
    -------
    float for a (3,) input, else (...,) array.
    """
    rmse_xyz = np.asarray(rmse_xyz, dtype=float)
    ref = np.asarray(ref, dtype=float)
    if rmse_xyz.shape[-1:] != (3,) or ref.shape != (3,) or np.any(ref <= 0):
        raise LboError(f"nrmse needs rmse (..., 3) and a positive reference (3,), "
                       f"got {rmse_xyz.shape} and {ref.tolist()}")
    out = np.sqrt(np.sum(rmse_xyz**2 / (3.0 * ref**2), axis=-1))
    return float(out) if out.ndim == 0 else out


def score_table(observer: str, est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None,
                alpha: np.ndarray, ref: ArrayLike = PAPER_REFERENCE) -> pd.DataFrame:
    """Score one observer on a grid of trajectories, one row per noise level alpha.

    The RMSE at an alpha pools every scored point of every trajectory at that alpha (it is
    not the mean of per-trajectory RMSEs), as the paper scores its test set.

    Parameters
    ----------
    observer : name written in the ``observer`` column.
    est, truth : (G, T, 3) estimates and true states.
    mask : (G, T) bool scored steps (e.g. False on padding), or None for all.
    alpha : (G,) noise level of each trajectory.
    ref : (3,) E_ref for the NRMSE.

    Returns
    -------
    DataFrame with columns ``observer, alpha, rmse_x, rmse_y, rmse_psi, nrmse`` (m, m, rad),
    sorted by alpha.
    """
    sq, mask = _squared_errors(est, truth, mask)
    if sq.ndim != 3:
        raise LboError(f"est and truth must be (G, T, 3), got {sq.shape}")
    alpha = np.asarray(alpha, dtype=float)
    if alpha.shape != sq.shape[:1]:
        raise LboError(f"alpha must be ({sq.shape[0]},), one per trajectory, got {alpha.shape}")
    # round so that 0.75 and 0.7500000000001 from different code paths are one level
    levels, group = np.unique(np.round(alpha, 9), return_inverse=True)
    sse = np.zeros((len(levels), 3))
    np.add.at(sse, group, sq.sum(axis=1))
    count = np.bincount(group, weights=mask.sum(axis=1), minlength=len(levels))
    with np.errstate(invalid="ignore", divide="ignore"):
        per_level = np.sqrt(sse / count[:, None])
    return pd.DataFrame({
        "observer": observer,
        "alpha": levels,
        "rmse_x": per_level[:, 0],
        "rmse_y": per_level[:, 1],
        "rmse_psi": per_level[:, 2],
        "nrmse": nrmse(per_level, ref) if len(levels) else np.empty(0),
    }, columns=SCORE_COLUMNS)


NEES_COLUMNS = ["observer", "alpha", "nees", "low", "high", "inside"]


def nees_table(observer: str, est: np.ndarray, cov: np.ndarray, truth: np.ndarray,
               mask: np.ndarray, alpha: np.ndarray, level: float = 0.95) -> pd.DataFrame:
    """Calibration of an observer's covariance, one row per noise level alpha.

    The normalised estimation error squared ``e^T P^-1 e`` of a consistent filter is
    chi-square with 3 degrees of freedom: its mean is 3. Each trajectory's NEES is averaged
    over its scored steps, and those means over the level's G trajectories, as G Monte Carlo
    runs (Bar-Shalom, Li and Kirubarajan, ch. 5.4): the two-sided ``level`` band of that mean
    is ``[chi2_{3G}((1 - level) / 2), chi2_{3G}((1 + level) / 2)] / G``. A trajectory's steps
    are strongly correlated, so it counts as one run, not as many.

    Parameters
    ----------
    est, truth : (G, T, 3); cov : (G, T, 3, 3) the observer's covariance of ``est``.
    mask : (G, T) scored steps; alpha : (G,) noise level of each trajectory.

    Returns
    -------
    DataFrame ``observer, alpha, nees, low, high, inside``, sorted by alpha; NaN where a level
    has no step with a positive-definite covariance (alpha = 0 for an oracle).
    """
    from scipy.stats import chi2

    err = np.asarray(est, float) - np.asarray(truth, float)
    err[..., 2] = wrap_angle(err[..., 2])
    cov = np.asarray(cov, float)
    ok = np.asarray(mask, bool) & np.isfinite(err).all(-1) & np.isfinite(cov).all((-1, -2))
    # a zero covariance (the oracle told alpha = 0) has no NEES: that level is left empty
    ok &= np.linalg.det(np.where(ok[..., None, None], cov, np.eye(3))) > 0
    safe = np.where(ok[..., None, None], cov, np.eye(3))
    e = np.where(ok[..., None], err, 0.0)
    nees = np.einsum("gti,gti->gt", e, np.linalg.solve(safe, e[..., None])[..., 0])
    per_traj = np.where(ok, nees, 0.0).sum(1) / np.maximum(ok.sum(1), 1)
    levels, group = np.unique(np.round(np.asarray(alpha, float), 9), return_inverse=True)
    rows = []
    for i, a in enumerate(levels):
        runs = per_traj[(group == i) & ok.any(1)]
        g = len(runs)
        # two quantiles: a (2,) array (scipy's stubs also allow a float)
        low, high = (cast(np.ndarray, chi2.ppf([(1 - level) / 2, (1 + level) / 2], 3 * g)) / g
                     if g else (np.nan, np.nan))
        mean = float(runs.mean()) if g else np.nan
        rows.append((observer, a, mean, low, high, bool(low <= mean <= high)))
    return pd.DataFrame(rows, columns=NEES_COLUMNS)
