"""Leave-one-drive-out: what was learned on some drives, scored on the one it never saw.

A noise learned on one drive and scored on a later span of the same drive fits that drive's
conditions (its stops, its receiver's sky), not the car. Across drives the honest score is
the one of each drive by a fit that never read it: for each drive in turn, learn on all the
others and score the one left out (:func:`leave_one_out`). Reported per drive, as the mean
over drives and as the worst (:func:`summary`): a fit that gains on average and loses on one
drive is not one to keep. Used by ``python -m lbo.realdrive`` on the hill drive's three
drives (:func:`lbo.logs.hguide.drives`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from lbo.core.errors import LboError
from lbo.filters.gyro_noise import GyroNoise
from lbo.scoring.receiver import EKF, ratio_to, score
from lbo.sim.vehicle import Vehicle

__all__ = ["Fold", "folds", "kept_apart", "leave_one_out", "markdown", "summary"]


class Fold(NamedTuple):
    """What a fold learned on its drives, by row label, to be scored on the one left out: the
    gyro EKF's noises, and learned observers (:class:`lbo.Observer`)."""

    noises: Mapping[str, GyroNoise]
    nets: Mapping[str, Any]


Learner = Callable[[int, list[pd.DataFrame]], Fold]
"""``learn(k, train)``: the :class:`Fold` learned for fold ``k`` on ``train``, the drives
other than ``k``."""


def folds(n: int) -> list[tuple[list[int], int]]:
    """The ``n`` folds of ``n`` drives: ``(train, test)``, the indices of every drive but
    ``test``, for ``test`` = 0 .. n-1. Needs two drives or more."""
    if n < 2:
        raise LboError(f"leave-one-drive-out needs two drives or more, got {n}")
    return [([i for i in range(n) if i != k], k) for k in range(n)]


def kept_apart(train: list[pd.DataFrame]) -> tuple[list[pd.DataFrame], list[pd.DataFrame]]:
    """A fold's drives as ``(learn on, keep the epoch by)``: all but the last, and the last
    (a drive the fit does not learn on, so an epoch that does not hold on another drive is
    not kept); one drive does both."""
    return (train[:-1], train[-1:]) if len(train) > 1 else (train, train)


def leave_one_out(drives: Sequence[pd.DataFrame], learn: Learner, observers: Sequence[str],
                  vehicle: Vehicle, noise: Any,
                  progress: Callable[[str], None] | None = print) -> pd.DataFrame:
    """Score each drive by what ``learn`` made of the others.

    drives : logs with truth (each scored from its own first course over ground on).
    learn : called once per fold with the fold's index and its training drives; never given
        the drive it is scored on.
    observers : the classical observers scored beside (:func:`lbo.scoring.receiver.score`:
        the raw fixes, each observer with the receiver's channels, the EKF blind and
        smoothed), the same on every drive.

    Returns one row per drive and estimator: ``drive`` (1-based), ``estimator``, ``x_m,
    y_m, psi_mrad, rows`` and ``vs_ekf`` (the measure against the kinematic EKF on that
    drive, :func:`lbo.scoring.receiver.ratio_to`)."""
    tables = []
    for train, k in folds(len(drives)):
        fold = learn(k, [drives[i] for i in train])
        table, _ = score(drives[k], observers, vehicle, noise, fold.noises, nets=fold.nets)
        table["vs_ekf"] = ratio_to(table, EKF)
        table.insert(0, "drive", k + 1)
        tables.append(table)
        if progress is not None:
            best = int(np.argmin(table["vs_ekf"].to_numpy(float)))
            progress(f"drive {k + 1} of {len(drives)}, learned on drives "
                     f"{', '.join(str(i + 1) for i in train)}: best "
                     f"{table['estimator'].iloc[best]} "
                     f"({table['vs_ekf'].iloc[best]:.3f} of the EKF)")
    return pd.concat(tables, ignore_index=True)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """:func:`leave_one_out`'s table as one row per estimator (in their first order): its
    ``vs_ekf`` on each drive (columns ``drive 1`` ... for numbered drives, else the drives'
    names, in their first order), their ``mean`` and the ``worst``."""
    order = list(dict.fromkeys(table["estimator"]))
    drives = list(dict.fromkeys(table["drive"]))
    wide = table.pivot(index="estimator", columns="drive", values="vs_ekf").loc[order, drives]
    wide.columns = [f"drive {d}" if isinstance(d, (int, np.integer)) else str(d)
                    for d in wide.columns]
    ratios = wide.to_numpy(float)
    wide["mean"] = ratios.mean(axis=1)
    wide["worst"] = ratios.max(axis=1)
    return wide.reset_index()


def markdown(wide: pd.DataFrame) -> str:
    """:func:`summary` as a markdown table (ratios to the EKF, two decimals)."""
    heads = [c for c in wide.columns if c != "estimator"]
    lines = ["| estimator | " + " | ".join(heads) + " |",
             "|---|" + "---:|" * len(heads)]
    for _, row in wide.iterrows():
        cells = [f"{row[c]:.3f}" if np.isfinite(row[c]) else "-" for c in heads]
        lines.append(f"| {row['estimator']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
