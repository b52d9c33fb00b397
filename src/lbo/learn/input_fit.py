"""The kinematic EKF's dead-reckoning terms, learned from a log's own fixes: a factor on the
speed, an offset and a factor on the steering.

Through a GNSS outage a filter runs on its motion model alone, and the kinematic bicycle's
model is only as good as its inputs: a CAN or wheel speed off by a percent or two, a
steering angle read with an offset and through a ratio the user guessed (the factor corrects
it). :class:`lbo.filters.inputs.InputTerms` undoes them (``V = speed_factor * V_logged``,
``delta = steering_factor * (delta_logged - steering_offset)``); :func:`fit` finds them on a
log without reading any truth, by the prediction-error method: the terms that make the EKF's
predicted positions land nearest the next fixes (the mean square of its position
innovations, at every update once the heading is known), searched by Nelder-Mead (SciPy)
from the terms given. The EKF is lbo's ``ekf`` (R at alpha = 1, the vehicle's and noise's),
on the log's receiver channels where it has them.

A log's gaps teach the most: over a second of dead reckoning between 1 Hz fixes a speed off
by 2% moves the prediction 0.3 m at 15 m/s. ``python -m lbo.observe observer=ekf adapt=true``
fits the terms to the log it observes and filters it with them; ``benchmarks/
outage_inputs.py`` measures what they buy through outages.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.inputs import InputTerms
from lbo.filters.stepper import run_stepper
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

__all__ = ["MAX_GAP_S", "TERMS", "UNITS", "Fitted", "fit", "innovations", "loss"]

TERMS = ("speed_factor", "steering_offset", "steering_factor")
"""What :func:`fit` may learn, each :class:`InputTerms`' field of that name."""
MAX_GAP_S = 2.0
"""The longest gap (s) after which a fix's innovation counts: the one after an outage measures
seconds of dead reckoning, with terms off by as much as the search may try from its start, and
its heavy tail took a search to the ranges' edges (30 s outages, a speed factor of 0.72)."""
UNITS = {"speed_factor": 0.01, "steering_offset": 0.005, "steering_factor": 0.01}
"""The search's units (a factor of 1%, 5 mrad of steering): Nelder-Mead's first simplex moves
each term by one unit, so that each starts as far from its start as the others."""


@dataclass(frozen=True, kw_only=True)
class Fitted:
    """:func:`fit`'s result: the terms, the mean square position innovation (m^2) at them and
    at the last search's start (over the fixes it counts), how many EKF runs the searches
    took, and how long (s)."""

    terms: InputTerms
    loss: float
    start_loss: float
    runs: int
    seconds: float


def _stacked(rows: np.ndarray | Sequence[np.ndarray], u: np.ndarray | Sequence[np.ndarray]
             ) -> tuple[np.ndarray, np.ndarray]:
    """One log (T, C) and (T, 2), or several (a list or tuple of each), as G logs from their first
    fixes, (G, T, C) and (G, T, 2): the shorter ones' ends padded with rows that hold nothing
    and inputs of standing still."""
    several = isinstance(rows, (list, tuple))
    logs = ([(np.asarray(r), np.asarray(v)) for r, v in zip(rows, u)] if several
            else [(np.asarray(rows), np.asarray(u))])
    cut = []
    for r, v in logs:
        fixed = np.isfinite(r[:, :2]).all(1)
        if fixed.sum() < 2:
            raise LboError("the inputs' terms are learned from the fixes, and a log has fewer "
                           "than two")
        cut.append((r[int(np.argmax(fixed)):], v[int(np.argmax(fixed)):]))
    t = max(len(r) for r, _ in cut)
    m = np.full((len(cut), t, cut[0][0].shape[1]), np.nan)
    uu = np.zeros((len(cut), t, 2))
    for g, (r, v) in enumerate(cut):
        m[g, :len(r)], uu[g, :len(v)] = r, v
    return m, uu


def innovations(rows: np.ndarray | Sequence[np.ndarray], u: np.ndarray | Sequence[np.ndarray],
                vehicle: Vehicle, noise: Noise, terms: InputTerms | None = None,
                max_gap_s: float = MAX_GAP_S) -> np.ndarray:
    """The EKF's position innovations (K, 2) (m) on a log, or on several at once (lists): at
    each update whose row holds a position, once the filter knows its heading (a single
    antenna's log learns it from the course over ground) and no more than ``max_gap_s`` after
    the fix before it, the fix less the position predicted on the inputs ``terms`` undo. rows
    (T, 3) ``[x_m, y_m, psi_m]`` or the filters' (T, 8) (:mod:`lbo.filters.measure`), u (T, 2)
    the logged ``[V, delta]``; ``terms`` None: as logged."""
    return _innovations(*_stacked(rows, u), vehicle, noise, terms, max_gap_s)


def _innovations(m: np.ndarray, logged: np.ndarray, vehicle: Vehicle, noise: Noise,
                 terms: InputTerms | None, max_gap_s: float) -> np.ndarray:
    """:func:`innovations` of G logs already stacked (:func:`_stacked`): m (G, T, C), the
    logged inputs (G, T, 2)."""
    uu = (terms or InputTerms()).undo(logged)
    kf = classical.stepper("ekf", m[:, 0], vehicle, noise)
    found: list[np.ndarray] = []
    gap = max_gap_s / vehicle.dt + 0.5  # steps, with room for rounding
    last = np.zeros(len(m))  # each log's row of the fix before

    def record(kf: Any, k: int | slice) -> None:
        if isinstance(k, int) and k > 0:
            fix = np.isfinite(m[:, k, :2]).all(1)
            counted = fix & (k - last <= gap) & ~kf.course.blind
            found.append(m[counted, k, :2] - kf.prior[0][counted, :2])
            last[fix] = k

    run_stepper(kf, m, uu, record=record)
    return np.concatenate(found).reshape(-1, 2) if found else np.zeros((0, 2))


def loss(rows: np.ndarray | Sequence[np.ndarray], u: np.ndarray | Sequence[np.ndarray],
         vehicle: Vehicle, noise: Noise, terms: InputTerms, max_gap_s: float = MAX_GAP_S
         ) -> float:
    """The prediction error :func:`fit` minimises: the mean square of :func:`innovations`
    (m^2); inf where there is none."""
    return _mean_square(innovations(rows, u, vehicle, noise, terms, max_gap_s))


def _mean_square(y: np.ndarray) -> float:
    return float(np.mean(y**2)) if len(y) else float("inf")


def fit(rows: np.ndarray | Sequence[np.ndarray], u: np.ndarray | Sequence[np.ndarray],
        vehicle: Vehicle, noise: Noise,
        start: InputTerms | None = None, free: tuple[str, ...] = TERMS,
        max_runs: int = 300) -> Fitted:
    """The terms (those named in ``free``, the others held at ``start``'s) that minimise
    :func:`loss` on one log, by Nelder-Mead from ``start`` (None: the terms that undo
    nothing; at most ``max_runs`` EKF runs a search). No truth is read. One line names a
    term lbo does not know or a log without two fixes.

    Two searches where the log has gaps longer than :data:`MAX_GAP_S` (outages): the first
    counts the fixes that follow a short gap only, the second, from where the first ended,
    every fix. The fix after a long gap measures its whole dead reckoning, so it tells the
    terms most finely (a steering offset off by 0.3 mrad turns the heading 0.05 rad in 30 s
    at 15 m/s); from terms far off it is only a heavy tail."""
    from scipy.optimize import minimize

    for name in free:
        if name not in TERMS:
            raise LboError(f"free: unknown term {name!r}; expected some of {', '.join(TERMS)}")
    m, logged = _stacked(rows, u)  # once for every run of the search; two fixes in every log
    began = time.perf_counter()
    start = start or InputTerms()
    at = {name: getattr(start, name) for name in free}
    scale = np.array([UNITS[name] for name in free])

    def terms_of(p: np.ndarray) -> InputTerms | None:
        try:
            return dataclasses.replace(start, **dict(zip(free, (p * scale).tolist())))
        except LboError:  # the search stepped outside the terms' ranges
            return None

    longest = max(np.diff(np.flatnonzero(np.isfinite(log[:, :2]).all(1))).max() for log in m)
    gaps = [MAX_GAP_S] + ([np.inf] if longest * vehicle.dt > MAX_GAP_S else [])
    p, runs = np.array([at[name] for name in free]) / scale, 0
    for gap in gaps:
        def objective(q: np.ndarray, gap: float = gap) -> float:
            terms = terms_of(q)
            return float("inf") if terms is None else _mean_square(
                _innovations(m, logged, vehicle, noise, terms, gap))

        first = objective(p)
        res = minimize(objective, p, method="Nelder-Mead",
                       options={"maxfev": max_runs, "xatol": 0.01, "fatol": 1e-6 * first})
        p, runs = res.x, runs + int(res.nfev) + 1
    best = terms_of(p) or start
    return Fitted(terms=best, loss=float(res.fun), start_loss=first, runs=runs,
                  seconds=time.perf_counter() - began)
