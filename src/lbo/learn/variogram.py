"""How far to trust a receiver's fixes, read from the fixes' variogram: no truth needed.

A receiver's position errors are slow (multipath, the atmosphere): each fix is off by nearly
what the one before it was. A filter that takes them as white noise of the reported accuracy
weighs ten fixes as ten independent ones and follows their common error; the likelihood of
its innovations, which sees only the small change from one fix to the next, rewards that (on
the hill drive the innovations' fit trusts the reported accuracy three times more, where the
fit against the truth trusts it half as much).

The errors' structure is observable without the truth. The receiver's own velocity (Doppler,
centimetres per second), integrated from fix to fix, moves as the antenna does, so a fix less
that integral is the fix's error plus a constant (:func:`offsets`). Half the mean square change
of that over a lag of ``h`` fixes, less what the velocity's reported noise adds to it, is the
errors' variogram ``gamma(h)`` (:func:`fix_errors`):
over one fix period the change from one fix to the next (``step``), and over lags longer than
the errors' correlation time their whole variance (``sill``). Taken as one first-order
process, the errors' correlation from one fix to the next is ``rho = 1 - step / sill``, and
the variance a filter that takes them as white should give each fix is their long-run
variance ``sill (1 + rho) / (1 - rho)`` (n of them averaged are as good as one of that
variance over n). :attr:`FixErrors.accuracy_scale` is the factor that makes the reported
accuracy that.

The course over ground is slow in the same way. Less the gyro's integrated turn it is the
course's error plus a constant (:func:`course_errors`), but its sill mixes the receiver's
error with what the car does (the antenna's path turns off its heading in a bend, the
course's variance already allows for that by its lever), so only the correlation is read
from it: the reported sigma of the course is widened by ``sqrt((1 + rho) / (1 - rho))``
(:attr:`Variogram.widening`). ``learn.receiver_noise=variogram`` sets the gyro EKF's two
factors on the receiver so (:func:`receiver_scales`) and learns the rest
(:func:`lbo.learn.gyro_fit.fit`).

On the hill drive the variogram of the fixes less the integrated velocity equals the one of
the fixes' error against the truth to 4 mm at one fix and within 20% over 10-30 s
(docs/logs.md, section 7).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError

__all__ = ["COURSE_SILL_S", "RECEIVER_NOISES", "SILL_S", "FixErrors", "Variogram",
           "course_errors", "fix_errors", "offsets", "receiver_scales"]

RECEIVER_NOISES = ("learned", "variogram")
"""How a fit of the gyro EKF's noise (:func:`lbo.learn.gyro_fit.fit`) finds the factors on the
receiver's reported accuracy and velocity sigma: learned with the other noises, or set from
its logs by :func:`receiver_scales` and kept while the rest is learned."""
SILL_S = (10.0, 20.0, 30.0)
"""Lags (s) whose variogram is pooled as the fixes' whole variance: longer than the
correlation time of a receiver's errors in the open (on the hill drive their correlation from
one fix to the one 10 s later is -0.03 to 0.48), short enough that the integrated velocity's
own error stays small beside them."""
COURSE_SILL_S = (5.0, 10.0, 20.0)
"""The same for the course, shorter: the gyro's bias, integrated, adds its square times the
lag's to the course's variogram."""


@dataclass(frozen=True, kw_only=True)
class Variogram:
    """Half the mean square change of a channel's error, pooled over its axes.

    step : over one period of the receiver; sill : over the lags that stand for its whole
    variance (units squared); pairs : how many pairs of consecutive samples ``step`` pools.
    """

    step: float
    sill: float
    pairs: int

    @property
    def rho(self) -> float:
        """The errors' correlation from one sample to the next, ``1 - step / sill``, in
        [0, 0.999] (a variogram above its sill at one step, a white error, reads as 0)."""
        return float(np.clip(1.0 - self.step / self.sill, 0.0, 0.999))

    @property
    def widening(self) -> float:
        """``sqrt((1 + rho) / (1 - rho))``: how much wider a sigma a filter that takes the
        errors as white should give each sample than their own."""
        return float(np.sqrt((1.0 + self.rho) / (1.0 - self.rho)))


@dataclass(frozen=True, kw_only=True)
class FixErrors(Variogram):
    """The fixes' variogram (m²) and ``reported`` (m²), the mean square of the accuracy the
    receiver reports for those fixes."""

    reported: float

    @property
    def long_run(self) -> float:
        """m², the variance a filter that takes the fixes as white should give each one:
        ``sill (1 + rho) / (1 - rho)``."""
        return self.sill * self.widening**2

    @property
    def accuracy_scale(self) -> float:
        """The factor on the reported accuracy that makes its variance :attr:`long_run`."""
        return float(np.sqrt(self.long_run / self.reported))


def offsets(t: np.ndarray, fix: np.ndarray, velocity: np.ndarray) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """Each fix less the receiver's velocity integrated from fix to fix (trapezoids): the
    fix's error plus a constant along each unbroken run of fixes.

    t : (K,) s, the fixes' times, increasing; fix : (K, 2) m ``[x_m, y_m]``;
    velocity : (K, 2) m/s ``[ve_m, vn_m]`` at those fixes (NaN: none, which breaks the run).

    Returns ``(d, run)``: d (K, 2) m, and run (K,) ints, the run each fix belongs to (a
    fix without a velocity is a run of its own; the constant differs from run to run)."""
    t, fix, velocity = (np.asarray(a, dtype=float) for a in (t, fix, velocity))
    step = 0.5 * (velocity[1:] + velocity[:-1]) * np.diff(t)[:, None]
    broken = ~np.isfinite(step).all(1)
    run = np.concatenate([[0], np.cumsum(broken)])
    moved = np.vstack([[0.0, 0.0], np.cumsum(np.where(broken[:, None], 0.0, step), axis=0)])
    return fix - moved, run


def _pairs(t: np.ndarray, run: np.ndarray, lag: int, period: float) -> np.ndarray:
    """(K - lag,) which samples pair with the one ``lag`` later: the same run, and ``lag``
    periods apart to half a period (a gap is no lag)."""
    if lag >= len(t):
        return np.zeros(0, dtype=bool)
    return (run[lag:] == run[:-lag]) & (np.abs(t[lag:] - t[:-lag] - lag * period)
                                        < 0.5 * period)


def _halved(t: np.ndarray, d: np.ndarray, run: np.ndarray, sv: np.ndarray, lag: int,
            period: float) -> np.ndarray:
    """(n, 2) m², half the square change of d over ``lag`` fixes (:func:`_pairs`), less what
    the velocity's own white noise adds to it: ``lag - 1/2`` periods' worth of its variance
    (sv (K,), its reported 1-sigma per axis) integrated by trapezoids, halved."""
    same = _pairs(t, run, lag, period)
    if not same.any():
        return np.empty((0, 2))
    change = (d[lag:] - d[:-lag])[same]
    walk = 0.5 * period**2 * (lag - 0.5) * 0.5 * (sv[lag:]**2 + sv[:-lag]**2)[same]
    return 0.5 * change**2 - walk[:, None]


def _logs(logs: pd.DataFrame | Sequence[pd.DataFrame], need: list[str], what: str
          ) -> list[pd.DataFrame]:
    logs = [logs] if isinstance(logs, pd.DataFrame) else list(logs)
    for i, log in enumerate(logs):
        missing = [c for c in need if c not in log]
        if missing:
            raise LboError(f"the {what} variogram reads a receiver's fixes, accuracy and "
                           f"velocity: log {i} has no {', '.join(missing)} column")
    return logs


def _pooled(parts: dict[str, list[np.ndarray]], lags: Sequence[float], what: str
            ) -> dict[str, np.ndarray]:
    """The parts concatenated, rows with a NaN left out; one line if too few pairs."""
    pooled = {k: np.concatenate(v) if v else np.empty((0, 2)) for k, v in parts.items()}
    pooled = {k: v[np.isfinite(v).all(1)] for k, v in pooled.items()}
    if len(pooled["step"]) < 10 or len(pooled["sill"]) < 10:
        raise LboError(f"the {what} variogram needs runs of fixes with a velocity over "
                       f"{max(lags):g} s or more: the logs give {len(pooled['step'])} "
                       f"pairs of consecutive fixes and {len(pooled['sill'])} over "
                       f"{', '.join(f'{s:g}' for s in lags)} s")
    return pooled


def _period(t: np.ndarray) -> float:
    return float(np.median(np.diff(t)))


def fix_errors(logs: pd.DataFrame | Sequence[pd.DataFrame],
               sill_s: Sequence[float] = SILL_S) -> FixErrors:
    """The variogram of the fixes of one log or several (``t, x_m, y_m, sx_m, sy_m, ve_m,
    vn_m``, and ``sv_m`` if the log has it, else :data:`lbo.filters.measure.SV_DEFAULT`; any
    truth columns are not read), pooled over the logs and both axes.

    The fix period is the median time between consecutive fixes; ``sill_s`` are seconds, each
    rounded to a whole number of periods."""
    from lbo.filters.measure import SV_DEFAULT

    logs = _logs(logs, ["t", "x_m", "y_m", "sx_m", "sy_m", "ve_m", "vn_m"], "fixes'")
    parts: dict[str, list[np.ndarray]] = {"step": [], "sill": [], "reported": []}
    for log in logs:
        rows = np.isfinite(log[["x_m", "y_m"]].to_numpy(float)).all(1)
        t = log["t"].to_numpy(float)[rows]
        if len(t) < 2:
            continue
        sv = log["sv_m"].to_numpy(float)[rows] if "sv_m" in log else np.full(len(t), np.nan)
        sv = np.where(np.isfinite(sv), sv, SV_DEFAULT)
        d, run = offsets(t, log[["x_m", "y_m"]].to_numpy(float)[rows],
                         log[["ve_m", "vn_m"]].to_numpy(float)[rows])
        parts["step"].append(_halved(t, d, run, sv, 1, _period(t)))
        parts["sill"] += [_halved(t, d, run, sv, max(1, round(s / _period(t))), _period(t))
                          for s in sill_s]
        parts["reported"].append(log[["sx_m", "sy_m"]].to_numpy(float)[rows])
    pooled = _pooled(parts, sill_s, "fixes'")
    step, sill = float(np.mean(pooled["step"])), float(np.mean(pooled["sill"]))
    if step <= 0 or sill <= 0:
        raise LboError(f"the fixes' variogram is not positive once the velocity's reported "
                       f"noise is taken out (one fix: {step:.3g} m², over "
                       f"{max(sill_s):g} s: {sill:.3g} m²): sv_m overstates it")
    return FixErrors(step=step, sill=sill, reported=float(np.mean(pooled["reported"]**2)),
                     pairs=len(pooled["step"]))


def course_errors(logs: pd.DataFrame | Sequence[pd.DataFrame],
                  sill_s: Sequence[float] = COURSE_SILL_S) -> Variogram:
    """The variogram (rad²) of the course over ground less the gyro's integrated turn, at
    the fixes that hold a course (:func:`lbo.filters.measure.course_over_ground`; ``t, ve_m,
    vn_m, V, r_m``, and ``sv_m``), pooled over one log or several; no truth read."""
    from lbo.filters.measure import course_over_ground

    logs = _logs(logs, ["t", "x_m", "ve_m", "vn_m", "V", "r_m"], "course's")
    parts: dict[str, list[np.ndarray]] = {"step": [], "sill": []}
    for log in logs:
        t_all, r = log["t"].to_numpy(float), log["r_m"].to_numpy(float)
        step = 0.5 * (r[1:] + r[:-1]) * np.diff(t_all)  # a row without the gyro breaks it
        turned = np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(step), step, 0.0))])
        runs = np.concatenate([[0], np.cumsum(~np.isfinite(step))])
        sv = log["sv_m"].to_numpy(float) if "sv_m" in log else np.full(len(log), np.nan)
        course, _ = course_over_ground(log["ve_m"].to_numpy(float), log["vn_m"].to_numpy(float),
                                       sv, log["V"].to_numpy(float))
        rows = np.flatnonzero(np.isfinite(log["x_m"].to_numpy(float)) & np.isfinite(course))
        if len(rows) < 2:
            continue
        t, d, run = t_all[rows], course[rows] - turned[rows], runs[rows]
        for key, lags in (("step", [_period(t)]), ("sill", sill_s)):
            for s in lags:
                lag = max(1, round(s / _period(t)))
                same = _pairs(t, run, lag, _period(t))
                change = wrap_angle(d[lag:] - d[:-lag])[same] if same.any() else np.empty(0)
                parts[key].append(0.5 * change[:, None]**2)
    pooled = _pooled(parts, sill_s, "course's")
    return Variogram(step=float(np.mean(pooled["step"])), sill=float(np.mean(pooled["sill"])),
                     pairs=len(pooled["step"]))


def receiver_scales(logs: pd.DataFrame | Sequence[pd.DataFrame]) -> tuple[float, float]:
    """``(accuracy_scale, velocity_scale)`` of the gyro EKF (:class:`lbo.filters.gyro_noise.
    GyroNoise`) the logs' receiver calls for: the fixes' :attr:`FixErrors.accuracy_scale` and
    the course's :attr:`Variogram.widening`."""
    return fix_errors(logs).accuracy_scale, course_errors(logs).widening
