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

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from lbo.core.errors import LboError
from lbo.scoring.metrics import rmse
from lbo.sim.columns import MEAS, RECEIVER, STATE

__all__ = ["BLANKED", "MOVING_SPEED", "Outages", "blank", "curves", "inside", "markdown",
           "place", "score", "windows"]

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


def windows(log: pd.DataFrame, outages: Outages, dt: float,
            first: int = 0) -> np.ndarray:
    """(K, 2) the outages' rows ``[start, end)`` in ``log``, in turn: each at the first row,
    ``every_s`` or more after the last one began (after row ``first`` for the first), from
    which the car's speed ``V`` stays at least :data:`MOVING_SPEED` for all of ``length_s``
    (a real drive moves in stretches between stops: a fixed grid would land on them)."""
    length, every = round(outages.length_s / dt), round(outages.every_s / dt)
    slow = np.r_[0, np.cumsum(~(np.abs(log["V"].to_numpy(float)) >= MOVING_SPEED))]
    k = np.arange(max(len(log) - length + 1, 0))
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
    spans = windows(log, outages, dt, first)
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
    last = spans[:, 1] - 1
    travelled = np.r_[0.0, np.cumsum(np.abs(log["V"].to_numpy(float)))] * dt
    driven = travelled[spans[:, 1]] - travelled[spans[:, 0]]  # m in each outage
    table = []
    for label, est in estimates.items():
        e = rmse(est, truth, rows)
        end = np.hypot(*(est[last, :2] - truth[last, :2]).T)
        table.append({"estimator": label, "outages": len(spans),
                      "position_m": float(np.hypot(e[0], e[1])),
                      "psi_mrad": 1e3 * float(e[2]),
                      "end_m": float(np.mean(end)), "end_worst_m": float(np.max(end)),
                      "drift_pct": 100 * float(np.mean(end / driven))})
    out = pd.DataFrame(table)
    if reference is not None:
        out[f"end_vs_{reference.split(',')[0]}"] = (
            out["end_m"] / out.loc[out["estimator"] == reference, "end_m"].iloc[0])
    return out


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
