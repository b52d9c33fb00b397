"""Scores on a receiver's log with truth: the raw fixes and every observer that reads one.

A single-antenna log (fixes without a heading, their reported accuracy, a GNSS velocity, a
gyro) is scored from its first course over ground on: before it, a car standing since the log
began, no single-antenna observer can know its heading. Each estimator's RMSE of x, y (m) and
psi (mrad) over the rows it estimates there; :func:`ratio_to` compares them, as the quadratic
mean over x, y and psi of the RMSE ratios to one row (the measure the real-drive and the
simulated-receiver targets are stated in). Used by ``python -m lbo.realdrive`` (the hill
drive) and ``python -m lbo.receiver_study`` (simulated logs, where an oracle can be run).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import pandas as pd

from lbo.core.errors import LboError
from lbo.filters import classical, measure
from lbo.filters.gyro import gyro_ekf_batch
from lbo.filters.gyro_noise import FixDrift, GyroNoise
from lbo.logs.io import receiver
from lbo.models.features import held_within
from lbo.scoring.metrics import rmse
from lbo.sim.columns import STATE
from lbo.sim.measurements import Measurements
from lbo.sim.vehicle import Vehicle

__all__ = ["BLIND", "EKF", "FULL_NOISE_ORACLE", "FULL_ORACLE", "NOISE_ORACLE", "ORACLE", "RAW",
           "load_nets", "markdown", "measure_ratio", "moving_rows", "oracle_gyro", "pool",
           "ratio_to", "score", "scored_rows"]

RAW = "raw fixes (heading: course over ground)"
"""The raw fixes' row: position at the fix rows; heading: the course of the receiver's
velocity, where the car moves fast enough for it to be one."""
EKF = "ekf, receiver's accuracy and velocity"
"""lbo's kinematic EKF with the receiver's channels: the real drive's reference row."""
BLIND = "ekf, lbo's R, no velocity"
"""The kinematic EKF without the receiver's channels (lbo's R, no velocity)."""
ORACLE = "oracle gyro EKF, told the true noise and bias"
""":func:`oracle_gyro`'s row, told the bias's value: the simulated logs' reference."""
NOISE_ORACLE = "oracle gyro EKF, told the true noise, bias estimated"
""":func:`oracle_gyro`'s row told the bias's statistics, not its value: the best a causal
filter that must learn the bias from the log can hope for."""
FULL_ORACLE = "oracle gyro EKF, told the noise, the fixes' drift and latency, and the bias"
""":func:`oracle_gyro`'s row told everything that drew the log: the noise, the fixes' drift
as two more states, the channels' latency and the bias's value."""
FULL_NOISE_ORACLE = ("oracle gyro EKF, told the noise, the fixes' drift and latency, "
                     "bias estimated")
""":data:`FULL_ORACLE`'s filter told the bias's statistics, not its value: what a causal
filter that knows everything else still loses by having to learn the bias."""
NET_ROW = "receiver's accuracy and velocity"
"""How a learned observer's row is labelled after its name and form."""
RMSE = ("x_m", "y_m", "psi_mrad")
"""A score table's RMSE columns."""
MOVING_S = 8.0
"""s: a row is *moving* (:func:`moving_rows`) when its last 8 s hold a course over ground."""


def _course(log: pd.DataFrame) -> np.ndarray:
    """(T,) the course over ground of a log's receiver velocity (NaN where it is none)."""
    meas = Measurements.from_frame(log)
    return measure.course_over_ground(meas.velocity[:, 0], meas.velocity[:, 1],
                                      meas.velocity_sigma, log["V"].to_numpy(float))[0]


def scored_rows(log: pd.DataFrame) -> np.ndarray:
    """(T,) bool: the rows from the log's first course over ground on, where a single-antenna
    observer can know the heading (a car standing since the log began cannot)."""
    course = _course(log)
    if not np.isfinite(course).any():
        raise LboError("the log never moves fast enough for a course over ground: a single "
                       "antenna tells no heading there")
    return np.arange(len(log)) >= int(np.argmax(np.isfinite(course)))


def load_nets(sources: Sequence[Any] | None) -> list[Any]:
    """The learned observers of a command's ``nets`` (checkpoints, run ids, ``models:/``
    URIs), each read once and before any work, so that a bad one fails at once."""
    from lbo.serve.observer import Observer

    return [Observer.load(str(source)) for source in sources or ()]


def net_rows(nets: Sequence[Any]) -> dict[str, Any]:
    """Learned observers by their row label, ``<name> (<form>), receiver's accuracy and
    velocity``; a window filter that reads a receiver in both its forms (the window form
    beside the recursive one it loads in)."""
    from lbo.serve.observer import Observer

    rows = {}
    for obs in nets:
        rows[f"{obs.name} ({obs.form}), {NET_ROW}"] = obs
        if obs.form == "recursive" and getattr(obs.net, "receiver", False):
            window = Observer.from_net(obs.net, obs.vehicle, obs.noise, form="window")
            rows[f"{window.name} (window), {NET_ROW}"] = window
    return rows


def score(log: pd.DataFrame, observers: Sequence[str], vehicle: Vehicle, noise: Any,
          learned: Mapping[str, GyroNoise] | None = None,
          extra: Mapping[str, np.ndarray] | None = None,
          nets: Sequence[Any] | Mapping[str, Any] = ()
          ) -> tuple[pd.DataFrame, dict[str, np.ndarray]]:
    """RMSE (x m, y m, psi mrad) of the raw fixes and each observer on ``log`` (with truth),
    every one scored from the log's first course over ground on.

    observers : classical observers run with the receiver's channels (:meth:`lbo.Observer.run`);
    then the EKF without them (lbo's R, no velocity) and smoothed (RTS, offline).
    learned : also the gyro EKF with each of these (learned) noises, by row label.
    extra : estimates (T, 3) made elsewhere (NaN: none yet), by row label.
    nets : learned observers (:class:`lbo.Observer`, loaded once by the caller) run with the
        receiver's channels (the robust observer's recursive form takes them), labelled by
        :func:`net_rows`; or such observers by row label.

    Returns the table (one row each: ``estimator, x_m, y_m, psi_mrad, rows``) and the
    estimates (T, 3) by row label (NaN where an observer has none yet, and on the rows not
    scored)."""
    from lbo.serve.observer import Observer

    m = log[["x_m", "y_m", "psi_m"]].to_numpy(dtype=float)
    u = log[["V", "delta"]].to_numpy(dtype=float)
    z = log[list(STATE)].to_numpy(dtype=float)
    r = receiver(log)
    course = _course(log)
    scored = scored_rows(log)  # every estimator alike, from the first course over ground
    fix = np.isfinite(m[:, :2]).all(1) & scored
    position = rmse(np.column_stack([m[:, :2], z[:, 2]]), z, fix)  # its psi error is 0
    heading = rmse(np.column_stack([z[:, :2], course]), z, np.isfinite(course))
    table = [{"estimator": RAW, "x_m": float(position[0]), "y_m": float(position[1]),
              "psi_mrad": 1e3 * float(heading[2]), "rows": int(fix.sum())}]
    runs: list[tuple[str, str, np.ndarray | None, bool, GyroNoise | None]] = [
        (f"{name}, receiver's accuracy and velocity", name, r, False, None)
        for name in observers]
    runs += [(label, classical.GYRO, r, False, gyro)
             for label, gyro in (learned or {}).items()]
    runs += [(BLIND, "ekf", None, False, None),
             ("ekf, receiver's channels, smoothed (RTS, offline)", "ekf", r, True, None)]
    found: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for label, name, channels, smooth, gyro in runs:
        obs = Observer.load(name, vehicle, noise, gyro_noise=gyro)
        found[label] = obs.run(m, u, receiver=channels, smooth=smooth)
    for label, obs in (nets if isinstance(nets, Mapping) else net_rows(nets)).items():
        found[label] = obs.run(m, u, receiver=r, source=str(obs.meta.get("source", obs.name)))
    for label, est in (extra or {}).items():
        found[label] = (est, np.isfinite(est).all(1))
    estimates = {}
    for label, (est, valid) in found.items():
        e = rmse(est, z, valid & scored)
        table.append({"estimator": label, "x_m": float(e[0]), "y_m": float(e[1]),
                      "psi_mrad": 1e3 * float(e[2]), "rows": int((valid & scored).sum())})
        estimates[label] = np.where((valid & scored)[:, None], est, np.nan)  # as scored
    return pd.DataFrame(table), estimates


def measure_ratio(est: np.ndarray, reference: np.ndarray, truth: np.ndarray,
                  rows: np.ndarray) -> float:
    """The quadratic mean over x, y and psi of the ratios of the RMSE of ``est`` to that of
    ``reference`` (each (T, 3)) against ``truth`` over ``rows`` (T,) bool."""
    return float(_quadratic_mean(rmse(est, truth, rows) / rmse(reference, truth, rows)))


def ratio_to(table: pd.DataFrame, label: str) -> np.ndarray:
    """(rows,) the quadratic mean over x, y and psi of each row's RMSE ratios to the row
    ``label`` (NaN throughout where the table has no such row)."""
    rmses = table[list(RMSE)].to_numpy(dtype=float)
    names = table["estimator"].to_list()
    if label not in names:
        return np.full(len(table), np.nan)
    return _quadratic_mean(rmses / rmses[names.index(label)])


def moving_rows(log: pd.DataFrame, dt: float, seconds: float = MOVING_S) -> np.ndarray:
    """(T,) bool: the rows whose last ``seconds`` (period ``dt`` s) hold a course over
    ground: the car moves, or stopped less than that long ago. The rest are stops, where a
    single antenna tells nothing of the heading and every observer holds the one it had."""
    return held_within(np.isfinite(_course(log)), max(int(round(seconds / dt)), 1))


def ratio_on_same_rows(table: pd.DataFrame, estimates: Mapping[str, np.ndarray],
                       truth: np.ndarray, label: str, within: np.ndarray | None = None
                       ) -> np.ndarray:
    """(rows,) each estimator's :func:`measure_ratio` to the row ``label``, both over the rows
    where both have an estimate (and ``within`` (T,) bool, if given): the fair measure for an
    observer that gives none on some rows. NaN for a row without estimates (the raw fixes) or
    where the table has no ``label``."""
    if label not in estimates:
        return np.full(len(table), np.nan)
    ref = estimates[label]
    held = np.isfinite(ref).all(1) & (True if within is None else within)
    out = []
    for name in table["estimator"]:
        est = estimates.get(name)
        if est is None:
            out.append(np.nan)
            continue
        rows = held & np.isfinite(est).all(1)
        out.append(measure_ratio(est, ref, truth, rows) if rows.any() else np.nan)
    return np.array(out)


def _quadratic_mean(ratios: np.ndarray) -> np.ndarray:
    """(..., 3) RMSE ratios of x, y and psi -> (...,) their quadratic mean: the measure."""
    return np.sqrt(np.mean(np.square(ratios), axis=-1))


def pool(tables: Sequence[pd.DataFrame]) -> pd.DataFrame:
    """One table of several logs' (same estimators, same order): each RMSE the root of the
    row-weighted mean of the squares, as if their scored rows were one log's."""
    if not tables or any(list(t["estimator"]) != list(tables[0]["estimator"]) for t in tables):
        raise LboError("pool: expected score tables of the same estimators, in one order")
    rows = np.stack([t["rows"].to_numpy(dtype=float) for t in tables])
    out = tables[0][["estimator"]].copy()
    weight = rows / np.maximum(rows.sum(0), 1.0)
    for c in RMSE:
        mse = np.stack([t[c].to_numpy(dtype=float) ** 2 for t in tables])
        out[c] = np.sqrt((weight * mse).sum(0))
    out["rows"] = rows.sum(0).astype(int)
    return out


def oracle_gyro(log: pd.DataFrame, vehicle: Vehicle, position_sigma: float,
                process_sigma: float, gyro_sigma: float,
                bias: tuple[float, float] | None = None, drift: FixDrift | None = None,
                latency: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The gyro EKF told what drew a simulated single-antenna log (``python -m lbo.simulate
    receiver=...``): estimates (T, 3).

    - With ``bias`` None, the gyro less its true bias (the log's ``b`` column), so its bias
      state starts and stays at 0 (sigma 1e-6 rad/s, no walk). With ``bias`` ``(sigma,
      walk)``, the gyro as logged, its bias a state that starts at N(0, sigma^2) rad/s and
      walks at ``walk`` rad/s/sqrt(s): told the bias's statistics, it learns the value from
      the log as any causal filter must (:data:`NOISE_ORACLE`).
    - Each fix's R is its true 1-sigma ``position_sigma`` (m) in place of the reported
      accuracy: alpha times the receiver's white noise and drift combined, or, told the
      ``drift`` (:class:`lbo.filters.gyro_noise.FixDrift`, two more states), its white part.
    - The process noise is the truth's on x and y (``process_sigma``, m a step) and none on the
      heading beyond the gyro's white noise ``gyro_sigma`` (rad/s): the gyro reads the true
      turn, process noise included.
    - The course's variance is the velocity's sigma over the speed, with no lever (the
      truth's point is the one the velocity is of).
    - Told the fixes' and the velocities' ``latency`` (s each), it brings them forward to
      their row (:func:`lbo.filters.measure.undelayed`, turned by the gyro).

    By default not told the drift's correlation in time (an EKF's R is white) nor the
    channels' latency, as no observer here is: :data:`ORACLE`; told both,
    :data:`FULL_ORACLE` and :data:`FULL_NOISE_ORACLE`. It is the plain EKF told these: its
    consistency test's remedy is off (``relearn``, :mod:`lbo.filters.consistency`), so a
    mismatch it is not told of (the latency) is not widened away."""
    if bias is None and "b" not in log:
        raise LboError("oracle_gyro: the log has no 'b' column (the gyro's true bias): "
                       "simulate it with a receiver (python -m lbo.simulate receiver=...)")
    meas = Measurements.from_frame(log)
    if not meas.has_fix[0]:
        raise LboError("oracle_gyro: the log's first row holds no fix")
    meas = replace(meas, fix_sigma=np.where(np.isfinite(meas.fix), position_sigma, np.nan))
    v = log["V"].to_numpy(dtype=float)
    rate = log["r_m"].to_numpy(float)
    if bias is None:
        rate = rate - log["b"].to_numpy(float)
        bias = (1e-6, 1e-12)
    if any(latency):
        fixes, velocity = measure.undelayed(meas.fix, meas.velocity, rate, *latency)
        meas = replace(meas, fix=fixes, velocity=velocity)
    rows = measure.rows(meas, v, np.zeros(len(v)), 0.0)
    Q = np.diag([process_sigma**2, process_sigma**2, 0.0])
    R = np.diag([position_sigma**2, position_sigma**2, 1.0])  # every fix reports its own
    return gyro_ekf_batch(rows[None], np.column_stack([v, rate])[None], vehicle, Q, R,
                          gyro_sigma=gyro_sigma, bias_sigma=bias[0], bias_walk=bias[1],
                          drift=drift, relearn=False).mean[0]


def markdown(table: pd.DataFrame, *versus: str) -> str:
    """The table as markdown, with its ratio columns ``versus`` (e.g. ``vs_ekf``)."""
    heads = "".join(f" {v.replace('_', ' ')} |" for v in versus)
    lines = [f"| estimator | x (m) | y (m) | psi (mrad) |{heads}",
             "|---|---:|---:|---:|" + "---:|" * len(versus)]
    lines += [f"| {r['estimator']} | {r['x_m']:.2f} | {r['y_m']:.2f} | {r['psi_mrad']:.1f} |"
              + "".join(f" {r[v]:.2f} |" if np.isfinite(r[v]) else " - |" for v in versus)
              for _, r in table.iterrows()]
    return "\n".join(lines) + "\n"
