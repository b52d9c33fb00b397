"""GNSS outages: windows in which a log's receiver falls silent, and how far each observer
drifts through them.

A car loses its fixes under bridges, in tunnels and between tall buildings; a filter then runs
on its motion model alone, and navigation papers report that drift first. The protocol
(:class:`Outages`): from the log's first course over ground on, every ``every_s`` seconds
while the car moves, a window of ``length_s`` seconds in which every receiver column is
blanked (:data:`BLANKED`: the fix, its reported accuracy, the GNSS velocity), the gyro, the
inputs and the truth kept (:func:`windows`, :func:`blank`). The observers run on the blanked
log as on any other; :func:`score` then reads, inside the windows only, the position and
heading RMSE, the position error at each window's end, and that error over the distance the
car travelled in the window (the drift per distance, %).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from lbo.core.errors import LboError
from lbo.scoring.metrics import rmse
from lbo.sim.columns import MEAS, RECEIVER, STATE
from lbo.sim.schema import Trajectories

__all__ = ["BLANKED", "MOVING_SPEED", "Outages", "blank", "blank_grid", "curves", "grid_inside",
           "grid_table", "grid_windows", "inside", "markdown", "place", "printable", "score",
           "score_grid", "windows"]

BLANKED = (*MEAS, *(c for c in RECEIVER if c != "r_m"))
"""The columns an outage blanks: what a GNSS receiver gives (the gyro is the car's own)."""
MOVING_SPEED = 1.0
"""Speed (m/s) the car holds through a whole window for an outage to be placed there: a
standing car's drift is not what the protocol measures."""


@dataclass(frozen=True)
class Outages:
    """Outages of ``length_s`` seconds, one every ``every_s`` seconds while the car moves."""

    length_s: float
    every_s: float

    def __post_init__(self) -> None:
        for name in ("length_s", "every_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1e6:
                raise LboError(f"outages.{name} must be a number of seconds > 0, got {v!r}")
        if self.every_s <= self.length_s:
            raise LboError(f"outages.every_s must be longer than outages.length_s (one outage "
                           f"ends before the next begins), got {self.every_s:g} <= "
                           f"{self.length_s:g}")

    @classmethod
    def from_cfg(cls, cfg: Any) -> Outages | None:
        """From a config group ``outages`` (``length_s``, ``every_s``); None where it is
        absent or its ``length_s`` is null or 0 (no outage)."""
        if cfg is None or not cfg.get("length_s"):
            return None
        return cls(length_s=cfg.length_s, every_s=cfg.get("every_s"))


def windows(speed: np.ndarray, outages: Outages, dt: float, first: int = 0) -> np.ndarray:
    """(K, 2) the outages' rows ``[start, end)`` in a log whose speed is ``speed`` (T,) m/s,
    in turn: each at the first row, ``every_s`` or more after the last one began (after row
    ``first`` for the first), from which the speed stays at least :data:`MOVING_SPEED` for
    all of ``length_s`` (a real drive moves in stretches between stops: a fixed grid would
    land on them)."""
    length, every = round(outages.length_s / dt), round(outages.every_s / dt)
    slow = np.r_[0, np.cumsum(~(np.abs(np.asarray(speed, float)) >= MOVING_SPEED))]
    k = np.arange(max(len(slow) - length, 0))
    fits = k[slow[k + length] - slow[k] == 0]  # no slow row in [k, k + length)
    starts: list[int] = []
    at = first + every
    while (i := np.searchsorted(fits, at)) < len(fits):  # one pass per outage, not per row
        starts.append(int(fits[i]))
        at = starts[-1] + every
    return np.array([[s, s + length] for s in starts], dtype=int).reshape(-1, 2)


def place(log: pd.DataFrame, outages: Outages, dt: float) -> np.ndarray:
    """:func:`windows` from the log's first course over ground on (where a receiver's log is
    scored from: :func:`lbo.scoring.receiver.scored_rows`), or from its first fix where it
    has no GNSS velocity; one line where none fits."""
    from lbo.scoring.receiver import scored_rows

    if {"ve_m", "vn_m"} <= set(log.columns):
        first = int(np.argmax(scored_rows(log)))
    else:
        first = int(np.argmax(np.isfinite(log[list(MEAS[:2])].to_numpy(float)).all(1)))
    spans = windows(log["V"].to_numpy(float), outages, dt, first)
    if not len(spans):
        raise LboError(f"outages: no window of {outages.length_s:g} s fits where the car moves "
                       f"(at least {MOVING_SPEED:g} m/s throughout); shorten outages.length_s")
    return spans


def inside(n: int, spans: np.ndarray) -> np.ndarray:
    """(n,) bool: the rows of a log of ``n`` rows within one of ``spans`` (K, 2)."""
    edges = np.zeros(n + 1, dtype=int)
    np.add.at(edges, spans[:, 0], 1)
    np.add.at(edges, spans[:, 1], -1)
    return np.cumsum(edges)[:n] > 0


def cut(log: pd.DataFrame, outages: Outages, dt: float) -> tuple[np.ndarray, pd.DataFrame]:
    """The outages' rows (K, 2) :func:`place` finds in ``log`` and the log :func:`blank` in
    them."""
    spans = place(log, outages, dt)
    return spans, blank(log, spans)


def blank(log: pd.DataFrame, spans: np.ndarray) -> pd.DataFrame:
    """A copy of ``log`` with the :data:`BLANKED` columns it holds NaN on the rows of
    ``spans`` (K, 2); every other column (the truth, the gyro, the inputs) as it was."""
    out = log.copy()
    rows = inside(len(log), spans)
    for c in BLANKED:
        if c in out:
            out[c] = out[c].to_numpy(float).copy()
            out.loc[rows, c] = np.nan
    return out


def curves(est: np.ndarray, truth: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """(K, L) the position error (m) through each outage, row by row from its first (NaN
    where the observer has no estimate); est, truth (T, 3); spans (K, 2) of L rows each."""
    rows = spans[:, :1] + np.arange(spans[0, 1] - spans[0, 0])
    return np.hypot(*(est[rows, :2] - truth[rows, :2]).transpose(2, 0, 1))


def _errors(est: np.ndarray, truth: np.ndarray, rows: np.ndarray, last: np.ndarray,
            driven: np.ndarray) -> dict[str, float]:
    """One estimator's errors through K outages: est, truth (N, 3); rows (N,) bool, the rows
    inside them; last (K,) each one's last row; driven (K,) m travelled in each."""
    e = rmse(est, truth, rows)
    end = np.hypot(*(est[last, :2] - truth[last, :2]).T)
    return {"outages": len(last), "position_m": float(np.hypot(e[0], e[1])),
            "psi_mrad": 1e3 * float(e[2]), "end_m": float(np.mean(end)),
            "end_worst_m": float(np.max(end)), "drift_pct": 100 * float(np.mean(end / driven))}


def _against(out: pd.DataFrame, reference: str | None, by: str | None = None) -> pd.DataFrame:
    """``end_vs_<reference>``: each row's ``end_m`` over the reference's (at the same ``by``,
    e.g. alpha, where given)."""
    if reference is None:
        return out
    mine = out["estimator"] == reference
    ref = out.loc[mine, "end_m"].iloc[0] if by is None else \
        out[by].map(out[mine].set_index(by)["end_m"])
    out[f"end_vs_{reference.split(',')[0]}"] = out["end_m"] / ref
    return out


def score(estimates: Mapping[str, np.ndarray], log: pd.DataFrame, spans: np.ndarray,
          dt: float, reference: str | None = None) -> pd.DataFrame:
    """Each observer's errors through the outages ``spans`` (K, 2) of ``log`` (which holds the
    truth and ``V``): one row per estimator of ``estimates`` ((T, 3) each, NaN: none).

    Columns: ``estimator``, ``outages`` (K), ``position_m`` and ``psi_mrad`` (the RMSE over
    the outages' rows), ``end_m`` (the mean position error at the outages' last rows),
    ``end_worst_m``, ``drift_pct`` (the mean of each end error over the distance driven in
    its outage, %), and with ``reference``, ``end_vs_<reference>`` (``end_m`` over the
    reference's)."""
    if not len(spans):
        raise LboError("outages: no window to score")
    truth = log[list(STATE)].to_numpy(float)
    rows = inside(len(log), spans)
    travelled = np.r_[0.0, np.cumsum(np.abs(log["V"].to_numpy(float)))] * dt
    driven = travelled[spans[:, 1]] - travelled[spans[:, 0]]  # m in each outage
    out = pd.DataFrame([{"estimator": label, **_errors(est, truth, rows, spans[:, 1] - 1,
                                                       driven)}
                        for label, est in estimates.items()])
    return _against(out, reference)


def grid_windows(arr: Trajectories, outages: Outages, dt: float) -> np.ndarray:
    """(K, 3) the outages of a simulated test grid ``arr``: each row a trajectory's index and
    an outage's rows ``[start, end)`` in it (:func:`windows` over its real rows, from its
    first fix on); one line where none fits in any trajectory."""
    found = []
    for g, n in enumerate(arr.lengths):  # per trajectory: each has its own speed profile
        first = int(np.argmax(np.isfinite(arr.m[g, :n, :2]).all(1)))
        w = windows(arr.u[g, :n, 0], outages, dt, first)
        found.append(np.c_[np.full(len(w), g), w])
    spans = np.concatenate(found).astype(int).reshape(-1, 3)
    if not len(spans):
        raise LboError(f"outages: no window of {outages.length_s:g} s fits in a test trajectory "
                       f"(one every {outages.every_s:g} s from its first fix, at least "
                       f"{MOVING_SPEED:g} m/s throughout); shorten outages.length_s or "
                       "outages.every_s")
    return spans


def grid_inside(shape: tuple[int, int], spans: np.ndarray) -> np.ndarray:
    """(G, T) bool: the rows of a (G, T) grid within one of ``spans`` (K, 3)."""
    edges = np.zeros((shape[0], shape[1] + 1), dtype=int)
    np.add.at(edges, (spans[:, 0], spans[:, 1]), 1)
    np.add.at(edges, (spans[:, 0], spans[:, 2]), -1)
    return np.cumsum(edges, axis=1)[:, :-1] > 0


def blank_grid(arr: Trajectories, spans: np.ndarray) -> Trajectories:
    """A copy of ``arr`` whose measurements (every fix channel) are NaN inside ``spans``
    (K, 3); the truth and the inputs as they were."""
    m = arr.m.copy()
    m[grid_inside(m.shape[:2], spans)] = np.nan
    return dataclasses.replace(arr, m=m)


def score_grid(estimates: Mapping[str, np.ndarray], arr: Trajectories, spans: np.ndarray,
               dt: float, reference: str | None = None,
               covariances: Mapping[str, np.ndarray] | None = None) -> pd.DataFrame:
    """Each observer's errors through the outages ``spans`` (K, 3) of the test grid ``arr``,
    per noise level: one row per estimator of ``estimates`` ((G, T, 3) each) and alpha, the
    columns of :func:`score` and ``alpha``; ``end_vs_<reference>`` at the same alpha. For an
    estimator with a covariance in ``covariances`` ((G, T, 3, 3)), its NEES over the rows
    inside the outages (:func:`lbo.scoring.metrics.nees_table`: ``nees``, 3 for an honest
    covariance, and its 95% band ``nees_low``, ``nees_high``; NaN for the others)."""
    from lbo.scoring.metrics import nees_table

    G, T = arr.m.shape[:2]
    flat = (spans[:, 0] * T)[:, None]  # each outage's rows in the (G * T) rows
    rows = grid_inside((G, T), spans)
    travelled = np.c_[np.zeros(G), np.cumsum(np.abs(arr.u[..., 0]), axis=1)] * dt
    driven = travelled[spans[:, 0], spans[:, 2]] - travelled[spans[:, 0], spans[:, 1]]
    truth = arr.z.reshape(-1, 3)
    table = []
    for alpha in np.unique(arr.alpha):
        at = arr.alpha[spans[:, 0]] == alpha  # this noise level's outages
        if not at.any():
            continue
        here = rows & (arr.alpha == alpha)[:, None]
        last = (flat[:, 0] + spans[:, 2] - 1)[at]
        for label, est in estimates.items():
            table.append({"estimator": label, "alpha": float(alpha),
                          **_errors(est.reshape(-1, 3), truth, here.reshape(-1), last,
                                    driven[at])})
    out = _against(pd.DataFrame(table), reference, "alpha")
    nees = [nees_table(name, estimates[name], cov, arr.z, rows & arr.mask, arr.alpha)
            for name, cov in (covariances or {}).items()]
    if not nees:
        return out.assign(nees=np.nan, nees_low=np.nan, nees_high=np.nan)
    held = pd.concat(nees).rename(columns={"observer": "estimator", "low": "nees_low",
                                            "high": "nees_high"})
    return out.merge(held[["estimator", "alpha", "nees", "nees_low", "nees_high"]],
                     on=["estimator", "alpha"], how="left")


def grid_table(arr: Trajectories, spans: np.ndarray, vehicle: Any, noise: Any,
               classical: list[str], learned: Mapping[str, Any], truth: Any = None
               ) -> pd.DataFrame:
    """Every observer run on the test grid ``arr`` with its fixes blanked in the outages
    ``spans`` (K, 3) and scored inside them (:func:`score_grid`, against the EKF where it is
    one): the ``learned`` nets (by label) in their default form, then the ``classical``
    observers by name (``truth``: what the set was drawn from, for the oracles of a car that
    slips). The covariance of each filter that gives one is checked by its NEES."""
    from lbo.filters.classical import OBSERVERS
    from lbo.filters.classical import estimate as run_classical
    from lbo.scoring.grid import classical as run
    from lbo.scoring.grid import predict_grid, predict_recursive
    from lbo.serve.runners import default_form

    blanked = blank_grid(arr, spans)
    estimates, covariances = {}, {}
    for label, net in learned.items():
        if default_form(net) == "recursive":
            estimates[label], cov, _ = predict_recursive(net, blanked)
            if cov is not None:  # a KalmanNet's carried form gives none
                covariances[label] = cov
        else:
            estimates[label] = predict_grid(net, blanked, net.window)
    for name in classical:
        if name in OBSERVERS:  # a covariance to check through the outages
            estimates[name], covariances[name] = run_classical(
                name, blanked.m, blanked.u, vehicle, noise, alpha=arr.alpha)
        else:
            estimates[name] = run(name, blanked, vehicle, noise, truth=truth)
    return score_grid(estimates, arr, spans, vehicle.dt,
                      reference="ekf" if "ekf" in estimates else None, covariances=covariances)


def printable(table: pd.DataFrame) -> str:
    """:func:`score_grid`'s table as a person reads it: the error at an outage's end per
    alpha, the NEES of those with a covariance and its band, and a line for each observer
    with no estimate inside the outages."""
    names = list(dict.fromkeys(table["estimator"]))
    held = table.dropna(subset=["nees"])
    with pd.option_context("display.width", 120, "display.precision", 3):
        lines = [table.pivot(index="alpha", columns="estimator", values="end_m")[names]
                 .to_string()]
        if len(held):
            lines += ["NEES inside the outages (3 for an honest covariance; the 95% band of "
                      "the level's mean beside it):",
                      held.pivot(index="alpha", columns="estimator", values="nees")[
                          list(dict.fromkeys(held["estimator"]))].join(
                          held.drop_duplicates("alpha").set_index("alpha")[
                              ["nees_low", "nees_high"]]).to_string()]
    none = table.groupby("estimator", sort=False)["end_m"].apply(lambda e: e.isna().all())
    lines += [f"note: {name} has no estimate inside the outages: a window net reads the fixes "
              "of its window and cannot coast without them" for name in none[none].index]
    return "\n".join(lines)


def markdown(table: pd.DataFrame) -> str:
    """The table of :func:`score` as markdown."""
    ratio = [c for c in table.columns if c.startswith("end_vs_")]
    head = "| estimator | position (m) | psi (mrad) | at the end (m) | worst end (m) | " \
           "drift (% of distance) |" + "".join(f" {c.replace('_', ' ')} |" for c in ratio)
    lines = [head, "|---|" + "---:|" * (5 + len(ratio))]
    for _, r in table.iterrows():
        lines.append(f"| {r['estimator']} | {r['position_m']:.2f} | {r['psi_mrad']:.1f} | "
                     f"{r['end_m']:.2f} | {r['end_worst_m']:.2f} | {r['drift_pct']:.2f} |"
                     + "".join(f" {r[c]:.2f} |" for c in ratio))
    return "\n".join(lines) + "\n"
