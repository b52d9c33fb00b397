"""The stepper contract of the classical filters, and the time loop that runs one over a log.

A classical observer is a *stepper*: an object built as ``Stepper(m0, vehicle, Q, R)`` from the
first rows m0 (G, 3) or (G, 8) of G trajectories (it starts there,
:func:`lbo.filters.start.start_state`), the vehicle, the process covariance Q (3, 3) and the
measurement covariance R (G, 3, 3), that then takes one time step per call:

- ``update(m, u_prev) -> x``: predict with the inputs u_{k-1} (G, 2), update with what row
  m_k (G, 3) or (G, 8) holds (NaN channels are not measured; :mod:`lbo.filters.measure`
  builds the step's H and R, :func:`lbo.filters.update.joseph_update` takes them); returns
  the estimate x_k (G, 3) and leaves it in ``x``, its covariance in ``P`` (G, 3, 3) (or
  wider, for steppers with more states: :func:`run_stepper` reads the pose through ``pose``
  and ``cov``);
- to be smoothed (:mod:`lbo.filters.smoother`), ``prior``: the ``(x, P)`` the last posterior
  came from, and ``cross``: ``cov(x_{k-1|k-1}, x_{k|k-1})`` (G, n, n);
- optionally ``coasts`` and ``coast(u)``: a run of prediction-only steps in one call;
- optionally ``reason(g) -> str | None``: why trajectory g's estimate is not to be trusted
  now, None when it is (the gyro EKF's consistency test, :mod:`lbo.filters.consistency`).

Every batch filter (:func:`lbo.filters.kalman.ekf_batch`, the UKF, the gyro EKF, the EKF on
the car that slips, a plug-in's) loops over its stepper with :func:`run_stepper`, and
:class:`lbo.Observer` steps the same stepper one sample at a time, so streaming and batch give
the same numbers. docs/plugins.md states the contract for a user's own observer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from tqdm.auto import tqdm

from lbo.filters.consistency import Checks


class _MeanCov(NamedTuple):
    mean: np.ndarray
    """(G, T, 3) the pose estimates ``[x, y, psi]``."""
    cov: np.ndarray
    """(G, T, 3, 3) their covariances: the filter's P of the pose (m^2, m rad, rad^2)."""


class Posterior(_MeanCov):
    """A batch filter's estimates with their covariances, what every batch filter returns (it
    unpacks as ``mean, cov``). ``checks`` (not unpacked): the consistency test of its
    innovations at every row (:class:`lbo.filters.consistency.Checks`) for a filter that
    makes one (the gyro EKF), else None."""

    checks: Checks | None

    def __new__(cls, mean: np.ndarray, cov: np.ndarray, checks: Checks | None = None
                ) -> Posterior:
        self = super().__new__(cls, mean, cov)
        self.checks = checks
        return self


Recorder = Callable[[Any, int | slice], None]
"""``record(kf, k)`` of :func:`run_stepper`."""


def run_stepper(kf: Any, m: np.ndarray, u: np.ndarray,
                pose: Callable[[Any], np.ndarray] = lambda kf: kf.x,
                cov: Callable[[Any], np.ndarray] = lambda kf: kf.P, smooth: bool = False,
                progress: str | None = None, lengths: np.ndarray | None = None,
                record: Recorder | None = None, stops: np.ndarray | None = None
                ) -> Posterior:
    """The time loop of a batch filter: a stepper ``kf`` started at ``m[:, 0]``, updated with
    every later step. ``pose(kf)`` (G, 3) and ``cov(kf)`` (G, 3, 3) read its estimate and
    covariance. Returns the :class:`Posterior` of the (G, T, 3) estimates and their
    (G, T, 3, 3) covariances (kept at every step: a copy of 9 numbers a trajectory, next to
    the step's arithmetic). With ``smooth`` (a stepper that records
    ``prior`` and ``cross``, of three states), the estimates and covariances are the RTS
    smoother's (:mod:`lbo.filters.smoother`).
    ``progress``: show a tqdm bar over the time steps with this name; ``lengths`` (G,): the
    real steps of padded trajectories, which the smoother does not smooth across;
    ``record(kf, k)``: called after the start (k = 0), each update (k) and each coast
    (k a slice of its rows), to keep what else the stepper says of a row; ``stops`` (T,)
    bool: rows no coast runs past, so that ``record`` sees the stepper's state there (a
    coast leaves it at its last row)."""
    from lbo.filters.smoother import rts

    g, t = m.shape[:2]
    est = np.empty((g, t, 3))
    est[:, 0] = pose(kf)
    covs = np.empty((g, t, 3, 3))
    covs[:, 0] = cov(kf)
    if record is not None:
        record(kf, 0)
    if smooth:
        x_p, P_p, cross = np.zeros_like(est), np.zeros_like(covs), np.zeros_like(covs)
    bar = tqdm(total=t - 1, desc=progress, unit="step", disable=progress is None,
               mininterval=2.0)
    # rows where no trajectory holds any channel: a stepper that can (``coasts``) takes each
    # run of them in one call (most rows of a log with 1-10 Hz fixes at 50 Hz)
    quiet = ~np.isfinite(m).any(axis=(0, 2))
    ends = quiet.copy()  # where a run may go on past a row: quiet, and not a stop
    if stops is not None:
        ends &= ~np.asarray(stops, dtype=bool)
    can_coast = not smooth and hasattr(kf, "coast")
    k = 1
    while k < t:
        if can_coast and quiet[k] and kf.coasts:
            end = k + 1 + int(np.argmin(np.append(ends[k:-1] & quiet[k + 1:], False)))
            est[:, k:end], covs[:, k:end] = kf.coast(u[:, k - 1:end - 1])
            if record is not None:
                record(kf, slice(k, end))
            bar.update(end - k)
            k = end
            continue
        kf.update(m[:, k], u[:, k - 1])
        est[:, k] = pose(kf)
        covs[:, k] = cov(kf)
        if record is not None:
            record(kf, k)
        if smooth:
            x_p[:, k], P_p[:, k] = kf.prior
            cross[:, k] = kf.cross
        bar.update(1)
        k += 1
    bar.close()
    if smooth:
        est, covs = rts(est, covs, x_p, P_p, cross, lengths=lengths)
    return Posterior(est, covs)
