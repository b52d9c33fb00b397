"""Observers scored on a data set's test grid: the classical filters, the learned nets' estimates
(window or recursive form), NRMSE against the reference EKF and the ratio to the oracle.

Every observer is scored on the same points: the ``scored`` rows of the test set (after each
manoeuvre's run-in), pooled per alpha level. `python -m lbo.evaluate` and the learned
observers' evaluation callback both score through here.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np
import pandas as pd

from lbo.core.atomic import atomic_path
from lbo.core.errors import LboError
from lbo.filters.classical import BOUND, NAMES, TUNED, measurement_cov, plugged
from lbo.filters.classical import estimate as run_classical
from lbo.filters.kalman import ekf_batch
from lbo.filters.pcrb import pcrb
from lbo.scoring import score_cache
from lbo.scoring.metrics import PAPER_REFERENCE, SCORE_COLUMNS, pooled_rmse, score_table
from lbo.sim import schema
from lbo.sim.columns import SCORED_SET
from lbo.sim.noise import Noise
from lbo.sim.schema import Trajectories
from lbo.sim.truth import Truth
from lbo.sim.vehicle import Vehicle

if TYPE_CHECKING:  # torch is imported where a net runs, not with the scoring
    from lbo.models.recursive import Filtered

REFERENCES = ("ekf", "paper")


Q_GRID = ((0.1, 0.3, 1.0, 3.0), (0.3, 1.0, 3.0, 10.0, 30.0))
"""Factors on the noise preset's process sigmas (position, heading) that ``oracle_tuned`` tries."""


def load_test(path: str | Path) -> Trajectories:
    """Read a test set (Parquet with the evaluation schema) into padded arrays
    (:class:`~lbo.sim.schema.Trajectories`: ``z, m`` (G, T, 3), ``u`` (G, T, 2), ``mask``
    (G, T) scored steps, ``alpha`` (G,), with G = trajectories x alpha levels). Steps without
    a position fix (``x_m, y_m, psi_m`` all empty) are NaN rows of ``m``."""
    return schema.to_arrays(schema.read_set(path, SCORED_SET, missing_fixes=True))


def classical(name: str, arr: Trajectories, vehicle: Vehicle, noise: Noise,
              progress: bool = False, seed: int = 0, truth: Truth | None = None) -> np.ndarray:
    """Estimates (G, T, 3) of classical observer ``name`` (:mod:`lbo.filters.classical`) on the
    padded test arrays; the oracles are told each trajectory's alpha (``oracle_dynamic`` also the
    ``truth`` the set was drawn from). For ``pcrb`` the result is the bound's standard
    deviation per step, not an estimate: the kinematic bicycle's, with the truth's own process
    noise, so it bounds nothing on a car that slips (refused there).
    """
    check_observers([name])
    if name == BOUND:
        if truth is not None and truth.car is not None:
            raise LboError("pcrb: the bound is the kinematic bicycle's; it bounds nothing on a "
                           "car that slips (car=dynamic)")
        R = measurement_cov("oracle", noise, arr.alpha, len(arr.alpha))
        scale = 1.0 if truth is None else truth.process_scale
        return np.sqrt(pcrb(arr.z, arr.u, vehicle, scale**2 * noise.Q, R, rng=seed))
    return run_classical(name, arr.m, arr.u, vehicle, noise, alpha=arr.alpha,
                         progress=progress, truth=truth).mean


def check_observers(names: Sequence[str], field: str = "observers") -> None:
    """Raise LboError naming ``field`` and the first name that is not a classical observer."""
    known = (*NAMES, *plugged())  # lbo's own and the installed plug-ins'
    for name in names:
        if name not in known:
            raise LboError(f"{field}: unknown observer {name!r}; "
                           f"expected names from {list(known)}")


def reference(arr: Trajectories, vehicle: Vehicle, noise: Noise,
              mode: str = "ekf") -> np.ndarray:
    """E_ref (3,) for the NRMSE: our EKF's RMSE at alpha=1 (``ekf``) or the paper's constants."""
    if mode == "paper":
        return np.asarray(PAPER_REFERENCE)
    if mode != "ekf":
        raise LboError(f"metric.reference must be one of {list(REFERENCES)}, got {mode!r}")
    at1 = np.isclose(arr.alpha, 1.0)
    if not at1.any():
        raise LboError("metric.reference=ekf needs alpha=1 in the test grid; "
                       "use metric.reference=paper")
    sub = arr.take(at1)
    est = run_classical("ekf", sub.m, sub.u, vehicle, noise).mean
    return pooled_rmse(est, sub.z, sub.mask)


def score(observer: str, est: np.ndarray, arr: Trajectories,
          ref: np.ndarray) -> pd.DataFrame:
    """Rows ``observer, alpha, rmse_x, rmse_y, rmse_psi, nrmse`` of estimates (G, T, 3).

    Steps outside ``arr.mask`` are ignored and may hold NaN.
    """
    return score_table(observer, est, arr.z, arr.mask, arr.alpha, ref)


def bound_table(std: np.ndarray, arr: Trajectories, ref: np.ndarray) -> pd.DataFrame:
    """PCRB rows: the root of the mean bound variance over the scored points of each level.

    Scoring ``truth + std`` as an estimate gives exactly that, since its squared error at
    each step is the bound's variance.
    """
    return score("pcrb", arr.z + std, arr, ref)


def classical_table(arr: Trajectories, vehicle: Vehicle, noise: Noise,
                    observers: Sequence[str] = NAMES, ref: np.ndarray | None = None,
                    progress: bool = False, seed: int = 0,
                    truth: Truth | None = None,
                    given: dict[str, np.ndarray] | None = None,
                    keep: Path | None = None) -> pd.DataFrame:
    """Score the classical observers on the test arrays; ``ref`` defaults to our EKF's;
    ``truth``: what the set was drawn from, for ``oracle_dynamic``; ``given``: estimates
    (G, T, 3) already made, by name, which are scored instead of running that filter again;
    ``keep``: the test set's file the arrays were read from, beside which lbo's own observers'
    rows are kept and read back (:mod:`lbo.scoring.score_cache`), None: always scored."""
    check_observers(observers)
    ref = reference(arr, vehicle, noise) if ref is None else ref
    given = given or {}

    def rows(name: str) -> pd.DataFrame:
        if name == TUNED:
            return score(name, tuned_oracle(arr, vehicle, noise, ref)[0], arr, ref)
        out = given.get(name)
        if out is None:
            out = classical(name, arr, vehicle, noise, progress=progress, seed=seed, truth=truth)
        return bound_table(out, arr, ref) if name == BOUND else score(name, out, arr, ref)

    tables = []
    for name in observers:
        if keep is None or name in given or name not in NAMES:  # a plug-in's: never kept
            tables.append(rows(name))
        else:
            tables.append(score_cache.cached(keep, name, (vehicle, noise, truth, seed), ref,
                                             functools.partial(rows, name)))
    return pd.concat(tables, ignore_index=True)[list(SCORE_COLUMNS)]


def tuned_oracle(arr: Trajectories, vehicle: Vehicle, noise: Noise,
                 ref: np.ndarray) -> tuple[np.ndarray, pd.DataFrame]:
    """The kinematic EKF told each level's alpha, its Q tuned per level on the scored points.

    Every pair of factors in :data:`Q_GRID` scales the preset's process sigmas (x and y by the
    first, psi by the second); at each alpha level the pair with the lowest NRMSE there wins.
    Returns the winners' estimates (G, T, 3) and a table ``alpha, position, heading`` of the
    factors chosen.
    """
    R = measurement_cov("oracle", noise, arr.alpha, len(arr.alpha))
    sigma = np.asarray(noise.process_sigma)
    best_est = np.full_like(arr.m, np.nan)
    best: dict[float, tuple[float, float, float]] = {}  # alpha -> (nrmse, position, heading)
    for fp in Q_GRID[0]:
        for fh in Q_GRID[1]:
            Q = np.diag(np.square(sigma * [fp, fp, fh]))
            est = ekf_batch(arr.m, arr.u, vehicle, Q, R).mean
            for a, nrmse in score(TUNED, est, arr, ref)[["alpha", "nrmse"]].itertuples(
                    index=False):
                if a not in best or nrmse < best[a][0]:
                    best[a] = (nrmse, fp, fh)
                    rows = np.isclose(arr.alpha, a)
                    best_est[rows] = est[rows]
    chosen = pd.DataFrame([(a, fp, fh) for a, (_, fp, fh) in sorted(best.items())],
                          columns=["alpha", "position", "heading"])
    return best_est, chosen


def nrmse_at(table: pd.DataFrame, observer: str, alpha: float) -> float:
    """The NRMSE of ``observer`` at ``alpha`` in a score table."""
    row = table[(table["observer"] == observer) & np.isclose(table["alpha"], alpha)]
    if row.empty:
        raise LboError(f"no row for observer {observer!r} at alpha={alpha}")
    return float(row["nrmse"].iloc[0])


def oracle_ratio(table: pd.DataFrame, observer: str, low: float = 0.25,
                 high: float = 6.0, oracle: str = "oracle") -> pd.Series:
    """NRMSE of ``observer`` over the oracle EKF's, per alpha in [low, high] (index alpha).

    The oracle is told each level's alpha, so it is the practical floor of a causal observer;
    a ratio of 1.1 means 10 % above that floor. ``oracle="oracle_dynamic"``: the floor on a
    car that slips.
    """
    piv = table.pivot_table(index="alpha", columns="observer", values="nrmse")
    for name in (observer, oracle):
        if name not in piv:
            raise LboError(f"no rows for observer {name!r} in the score table")
    keep = (piv.index >= low - 1e-9) & (piv.index <= high + 1e-9)
    return (piv[observer] / piv[oracle])[keep].rename(f"ratio_to_{oracle}")


def summary(table: pd.DataFrame, observer: str, alphas: Sequence[float] = (1.0, 3.0, 6.0),
            peers: Sequence[str] = ("ekf", "oracle"), oracle: str = "oracle",
            reference: str = "ekf") -> str:
    """A few lines for the end of a training run: the NRMSE of ``observer`` and ``peers`` at
    each of ``alphas`` the table holds, and the worst ratio of ``observer`` to ``oracle`` over
    alpha in [0.25, 6] (where the table holds the oracle); ``reference``: the table's E_ref
    (:func:`reference`'s mode), named in the first line."""
    by = ("the EKF at alpha 1 is 1" if reference == "ekf" else
          "E_ref: the paper's EKF, " + ", ".join(f"{v:g} {u}" for v, u in zip(
              (PAPER_REFERENCE[0], PAPER_REFERENCE[1], PAPER_REFERENCE[2] * 1e3),
              ("m", "m", "mrad"))))
    shown = [a for a in alphas if np.isclose(table["alpha"], a).any()]
    names = [observer, *(p for p in peers if (table["observer"] == p).any())]
    width = max(len(n) for n in names)
    lines = [f"NRMSE on the test grid (lower is better; {by}):",
             f"  {'observer':<{width}}" + "".join(f"  {f'alpha {a:g}':>9}" for a in shown)]
    lines += [f"  {n:<{width}}" + "".join(f"  {nrmse_at(table, n, a):>9.3f}" for a in shown)
              for n in names]
    if (table["observer"] == oracle).any():
        ratio = oracle_ratio(table, observer, oracle=oracle)
        if len(ratio):
            worst = float(cast(float, ratio.idxmax()))  # an alpha
            lines.append(f"  worst ratio to the {oracle} over alpha 0.25-6: {ratio.max():.3f} "
                         f"(at alpha {worst:g})")
    return "\n".join(lines)


def calibration(covariant: dict[str, tuple[np.ndarray, np.ndarray]], arr: Trajectories,
                out: Path) -> pd.DataFrame:
    """NEES per alpha of every observer that gives a covariance
    (:func:`lbo.scoring.metrics.nees_table`); writes ``nees.csv`` and ``nees.png`` to ``out``
    and prints the table."""
    from lbo.core import plots
    from lbo.scoring.metrics import nees_table

    table = pd.concat([nees_table(name, est, cov, arr.z, arr.mask, arr.alpha)
                       for name, (est, cov) in covariant.items()], ignore_index=True)
    with atomic_path(out / "nees.csv") as tmp:
        table.to_csv(tmp, index=False)
    plots.save(plots.nees_curves(table), out / "nees.png")
    with pd.option_context("display.width", 120, "display.precision", 3):
        print("mean NEES per alpha (3 for a consistent filter; the 95% band of a mean over "
              "the level's trajectories in brackets):")
        piv = table.pivot(index="alpha", columns="observer", values="nees")
        band = table.drop_duplicates("alpha").set_index("alpha")[["low", "high"]]
        print(piv.join(band).to_string())
    print(f"calibration: {out / 'nees.csv'}")
    return table


def learned_nets(sources: Sequence[str]) -> dict:
    """name (``cnn-N20``, ...) -> the net of each learned observer in ``sources`` (checkpoint
    files, MLflow run ids, runs:/ or models:/ URIs), all read before any scoring starts."""
    from lbo.tracking.artifacts import load_net

    nets: dict = {}
    for source in sources:
        net, hp = load_net(source)
        name = base = f"{hp['model']['name']}-N{hp['window']}"
        i = 2
        while name in nets:  # two observers of one architecture and window
            name, i = f"{base}-{i}", i + 1
        nets[name] = net
    return nets


def predict_recursive(net, arr: Trajectories, device: str = "cpu",
                      smooth: bool = False) -> Filtered:
    """A learned observer in its recursive form over every trajectory of the padded test
    arrays, all at once: its :class:`~lbo.models.recursive.Filtered`, (G, T, 3) estimates,
    (G, T, 3, 3) covariances and the (G, T, 2) body it carries, NaN outside the scored steps
    (``smooth``: the RTS smoother's estimates and covariances). The window filter (an
    WindowNet of ``filternet``) gives all three; a model carried otherwise (KalmanNet's peers,
    :mod:`lbo.models.carried`) gives no covariance (None), its body only around the
    single-track body (else None), and nothing to smooth."""
    from lbo.models.recursive import Filtered
    from lbo.serve.runners import is_window_filter

    if not is_window_filter(net):
        from lbo.models.carried import in_float64
        from lbo.models.carried import run_arrays as run_carried

        if smooth:
            raise LboError(f"smooth: {type(net.net).__name__} has no covariance to smooth with")
        est, body = run_carried(in_float64(net.net).to(device), arr.m, arr.u, device)
        est[~arr.mask] = np.nan
        est = np.where(np.isfinite(est), est, np.nan)
        return Filtered(est, None, None if body is None else np.where(
            np.isfinite(est[..., :1]), body, np.nan))
    from lbo.models.recursive import run_arrays

    out = run_arrays(net.net, arr.m, arr.u, smooth, arr.lengths, device)
    for part in out:
        part[~arr.mask] = np.nan
    return out


def predict(net, arr: Trajectories, batch_size: int = 8192,
            device: str = "cpu") -> np.ndarray:
    """A learned observer's estimates (G, T, 3) on the padded test arrays, in the form
    :class:`lbo.Observer` runs it by default (:func:`lbo.serve.runners.default_form`)."""
    from lbo.serve.runners import default_form

    if default_form(net) == "recursive":
        return predict_recursive(net, arr, device)[0]
    return predict_grid(net, arr, net.window, batch_size, device)


def predict_grid(net, arr: Trajectories, window: int, batch_size: int = 8192,
                 device: str = "cpu") -> np.ndarray:
    """Run a learned observer on every scored step of the padded test arrays.

    Parameters
    ----------
    net : a module mapping windows (B, N, 5) to states (B, 3), e.g. an WindowNet.
    arr : padded test arrays from :func:`load_test`.

    Returns
    -------
    (G, T, 3) estimates at the scored steps, NaN elsewhere.
    """
    import torch

    from lbo.models.features import window_view

    g, t = arr.mask.shape
    if window - 1 > int(np.argmax(arr.mask, axis=1).min()):
        raise LboError(f"window={window} is longer than the test set's run-in")
    series = torch.from_numpy(np.concatenate([arr.m, arr.u], axis=-1))  # (G, T, 5)
    windows = window_view(series, window)  # (G, T-N+1, N, 5) view
    gi, ti = np.nonzero(arr.mask)
    est = np.full((g, t, 3), np.nan)
    net = net.to(device).eval()
    with torch.inference_mode():
        for s in range(0, len(gi), batch_size):
            a, b = gi[s:s + batch_size], ti[s:s + batch_size] - window + 1
            win = windows[a, b].to(device)
            est[gi[s:s + batch_size], ti[s:s + batch_size]] = net(win).cpu().numpy()
    return est
