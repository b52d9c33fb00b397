"""The NumPy gyro EKF over the logs a noise fit reads (:mod:`lbo.learn.gyro_fit`): their
estimates, and the segments its torch twin learns on with the states they start from.

Every log of a call runs in one batch of the filter (each its own trajectory, padded to the
longest), so a fit on several drives loops over the time steps of one drive, not of them all:
the filter is recursive, so its Python loop is over time (the rows between fixes taken a run at
a time, :meth:`lbo.filters.gyro.GyroStepper.coast`), and everything else is an array op across
the logs. Each trajectory is independent of the others in the batch (its own update,
consistency window and course start), so a log's numbers are those it has alone, to rounding
(which rows coast, and which step one by one, depends on every log's fixes and standstills).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd
import torch

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical, measure
from lbo.filters.gyro_noise import GyroNoise
from lbo.filters.stepper import run_stepper
from lbo.models.gyro_filter import Segments
from lbo.scoring.receiver import scored_rows
from lbo.sim.columns import STATE
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

__all__ = ["as_logs", "estimates", "segments"]


def as_logs(logs: pd.DataFrame | Sequence[pd.DataFrame]) -> list[pd.DataFrame]:
    """One log or several, as a list."""
    return [logs] if isinstance(logs, pd.DataFrame) else list(logs)


def _columns(log: pd.DataFrame) -> tuple[Measurements, np.ndarray]:
    """The log's measurements (T steps) and inputs u (T, 2) ``[V, r_m]``."""
    if "r_m" not in log:
        raise LboError("the gyro EKF's noise is learned from a log with a gyro: no r_m column")
    meas = Measurements.from_frame(log)
    if meas.has_heading.any():
        raise LboError("the gyro EKF's noise is learned from single-antenna logs: psi_m must "
                       "be empty")
    return meas, log[["V", "r_m"]].to_numpy(dtype=float)


def _truth(log: pd.DataFrame) -> np.ndarray:
    """The log's truth (T, 3) ``[x, y, psi]``; NaN where it has none (a fleet's log: learned
    from its innovations)."""
    if all(c in log for c in STATE):
        return log[list(STATE)].to_numpy(float)
    return np.full((len(log), len(STATE)), np.nan)


def _preset(noise: GyroNoise, R: np.ndarray) -> Noise:
    """The classical observers' noise preset that carries R (3, 3), the fixes' covariance
    where one reports no accuracy (the gyro EKF takes its Q from ``noise``)."""
    return Noise(process_sigma=tuple(np.sqrt(np.diag(noise.Q))),
                 measurement_sigma=tuple(np.sqrt(np.diag(R))))


def _padded(parts: list[np.ndarray], fill: float) -> np.ndarray:
    """(G, T, C) the arrays (T_g, C) stacked, each padded with ``fill`` to the longest."""
    out = np.full((len(parts), max(len(p) for p in parts), parts[0].shape[1]), fill)
    for g, p in enumerate(parts):
        out[g, :len(p)] = p
    return out


def estimates(logs: pd.DataFrame | Sequence[pd.DataFrame], noise: GyroNoise, vehicle: Vehicle,
              R: np.ndarray) -> list[np.ndarray]:
    """The gyro EKF's estimates (T_g, 3) of each log under ``noise`` (NaN before its first
    fix); R (3, 3): the fixes' covariance where one reports no accuracy."""
    logs = as_logs(logs)
    read = [_columns(log) for log in logs]
    rows = _padded([measure.widen(noise.rows(meas, u)) for meas, u in read], np.nan)
    est = classical.estimate(classical.GYRO, rows, _padded([u for _, u in read], 0.0),
                             vehicle, _preset(noise, R), gyro=noise).mean
    return [est[g, :len(log)] for g, log in enumerate(logs)]


def segments(logs: pd.DataFrame | Sequence[pd.DataFrame], noise: GyroNoise, vehicle: Vehicle,
             R: np.ndarray, length: int) -> Segments:
    """The scored rows of each log cut into segments of ``length`` steps (its last, shorter
    one dropped), each started from the NumPy gyro EKF's state under ``noise`` at its first
    step; the logs' segments in turn, each log's in time order."""
    logs = as_logs(logs)
    read = [_columns(log) for log in logs]
    rows = [measure.widen(noise.rows(meas, u)) for meas, u in read]
    starts, begins = [], []
    for log, r in zip(logs, rows):
        first = int(np.argmax(scored_rows(log)))
        starts.append(np.arange(first, len(log) - length + 1, length))
        if not len(starts[-1]):
            raise LboError(f"the log has {len(log) - first} steps from its first course over "
                           f"ground, fewer than one segment of {length}")
        begins.append(int(np.argmax(np.isfinite(r[:, 0]) & np.isfinite(r[:, 1]))))
    # each log from its first fix to its last segment's start, all in one batch
    m = _padded([r[b:s[-1] + 1] for r, b, s in zip(rows, begins, starts)], np.nan)
    u = _padded([u[b:s[-1] + 1] for (_, u), b, s in zip(read, begins, starts)], 0.0)
    flt = classical.stepper(classical.GYRO, m[:, 0], vehicle, _preset(noise, R), gyro=noise)
    # which log's state each segment starts from, at which step of the batch
    log_of = np.concatenate([np.full(len(s), g) for g, s in enumerate(starts)])
    step_of = np.concatenate([s - b for s, b in zip(starts, begins)])
    x0 = np.empty((len(log_of),) + flt.x.shape[1:])
    P0 = np.empty((len(log_of),) + flt.P.shape[1:])
    taken = {int(k): np.flatnonzero(step_of == k) for k in np.unique(step_of)}

    def keep(kf: Any, k: int | slice) -> None:  # the state at a segment's first step
        now = taken.get(k.stop - 1 if isinstance(k, slice) else k)
        if now is not None:
            x0[now], P0[now] = kf.x[log_of[now]], kf.P[log_of[now]]

    run_stepper(flt, m, u, pose=lambda kf: kf.x[:, :3], cov=lambda kf: kf.P[:, :3, :3],
                record=keep, stops=np.isin(np.arange(m.shape[1]), step_of))
    parts = []
    for (meas, u_g), log, s in zip(read, logs, starts):
        idx = s[:, None] + np.arange(length)
        sigma = np.where(np.isfinite(meas.velocity_sigma), meas.velocity_sigma,
                         measure.SV_DEFAULT)
        ve, vn = meas.velocity[:, 0], meas.velocity[:, 1]
        heading = np.arctan2(vn, ve) + np.where(u_g[:, 0] < 0, np.pi, 0.0)
        parts.append([meas.fix[idx], meas.fix_sigma[idx], wrap_angle(heading)[idx],
                      np.hypot(ve, vn)[idx], sigma[idx], u_g[idx], _truth(log)[idx]])
    joined = [torch.as_tensor(np.ascontiguousarray(np.concatenate(f)), dtype=torch.float64)
              for f in zip(*parts)]
    return Segments(torch.as_tensor(x0), torch.as_tensor(P0), *joined)
