"""The consistency test of a Kalman filter's innovations, and the response to a failed one.

While a filter's covariance explains its innovations, each update's normalised innovation
squared ``NIS = y^T S^-1 y`` (:func:`lbo.filters.update.joseph_update` gives it) is
chi-square with as many degrees of freedom as the update measured channels, and the NIS of
successive updates are independent (a consistent filter's innovations are white). Their sum
over the last :data:`WINDOW` updates is then chi-square with the sum of their degrees of
freedom, and lies beyond that distribution's :data:`SIGNIFICANCE` quantile once in a
thousand tests. :class:`NisWindow` keeps that sum for G trajectories and flags a trajectory
whose sum lies beyond it: its innovations are larger than its covariance can explain (the
windowed NIS test of Bar-Shalom, Li and Kirubarajan, *Estimation with Applications to
Tracking and Navigation*, 2001, section 5.4). A flag holds from the update that raised it to
the next update, whose own test clears or keeps it.

A sum over a window, not each NIS alone: one gross innovation still fails it (a NIS of 100
alone is beyond the bound of any ten fixes), and innovations a few times larger than S says,
which no single update would show, fail it as they add up.

The response, :func:`widen`: scale the rows and columns of the states that can explain the
innovations (the gyro EKF's heading and bias, :mod:`lbo.filters.gyro`) by the square root of
the window's NIS per degree of freedom, the factor by which its innovations outgrew their
covariance, and start a new window. A filter sure of a wrong state (a gyro bias far beyond
its prior) learns it again; this is the covariance reset of a fading-memory filter, its
factor the adaptive one of a strong tracking filter (Zhou and Frank, 1996).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

WINDOW = 10
"""Updates (rows that measured any channel) the NIS is summed over: ten 1 Hz fixes."""
SIGNIFICANCE = 0.999
"""The chi-square quantile the window's NIS is tested against: a consistent filter fails one
test in a thousand."""


@functools.cache
def chi2_bounds(dof_max: int, significance: float = SIGNIFICANCE) -> np.ndarray:
    """(dof_max + 1,) the ``significance`` quantile of chi-square with 0 .. dof_max degrees
    of freedom (inf at 0: an empty window fails nothing); made once per filter's shape."""
    from scipy.stats import chi2  # here: importing the filters does not load scipy.stats

    bounds = np.full(dof_max + 1, np.inf)
    bounds[1:] = chi2.ppf(significance, np.arange(1, dof_max + 1))
    bounds.flags.writeable = False
    return bounds


def describe(nis: float, dof: int, updates: int, significance: float = SIGNIFICANCE) -> str:
    """The reason a row is flagged, of the window's NIS, its degrees of freedom and updates."""
    bound = chi2_bounds(int(dof), significance)[int(dof)]
    return (f"innovations inconsistent with the covariance: NIS {nis:.4g} over the last "
            f"{updates} update{'s' if updates != 1 else ''} ({dof} degrees of freedom), "
            f"beyond the {significance:.1%} chi-square bound {bound:.4g}")


class Checks(NamedTuple):
    """A batch filter's consistency test at every row of G trajectories of T rows: the
    window the last test read (its NIS, degrees of freedom and updates) and its result."""

    inconsistent: np.ndarray
    """(G, T) bool: the last test before (or at) the row failed."""
    nis: np.ndarray
    """(G, T) the window's NIS at that test."""
    dof: np.ndarray
    """(G, T) int, its degrees of freedom (0: no test yet)."""
    updates: np.ndarray
    """(G, T) int, the updates it held."""

    def reason(self, g: int, k: int) -> str | None:
        """Why row k of trajectory g is flagged (:func:`describe`), None where it is not."""
        if not self.inconsistent[g, k]:
            return None
        return describe(float(self.nis[g, k]), int(self.dof[g, k]), int(self.updates[g, k]))

    @classmethod
    def empty(cls, g: int, t: int) -> Checks:
        """No test at any row yet (filled row by row by :meth:`NisWindow.record`)."""
        return cls(np.zeros((g, t), bool), np.zeros((g, t)), np.zeros((g, t), np.int64),
                   np.zeros((g, t), np.int64))


class NisWindow:
    """The NIS of the last ``window`` updates of G trajectories, tested at every update.

    Parameters
    ----------
    g : trajectories.
    channels : the most channels one update measures (sizes the table of bounds).
    window, significance : :data:`WINDOW`, :data:`SIGNIFICANCE`.

    Attributes
    ----------
    inconsistent : (G,) bool, the last test failed (held between updates).
    nis, dof, updates : (G,) the window the last test read: its NIS, degrees of freedom and
        updates (kept when :meth:`clear` starts a new window, for the reason).
    """

    def __init__(self, g: int, channels: int, *, window: int = WINDOW,
                 significance: float = SIGNIFICANCE) -> None:
        self.window, self.significance = window, significance
        self.bounds = chi2_bounds(channels * window, significance)
        self.ring = np.zeros((g, window))                # each update's NIS, oldest overwritten
        self.ring_dof = np.zeros((g, window), np.int64)  # and its degrees of freedom
        self.head = np.zeros(g, np.int64)                # the slot the next update takes
        self.inconsistent = np.zeros(g, bool)
        self.nis, self.dof = np.zeros(g), np.zeros(g, np.int64)
        self.updates = np.zeros(g, np.int64)

    def push(self, nis: np.ndarray, dof: np.ndarray) -> np.ndarray:
        """Test the windows of the trajectories that updated: ``nis`` (G,) and ``dof`` (G,)
        int of this step (dof 0: no update, nothing changes). Returns :attr:`inconsistent`."""
        rows = np.flatnonzero(dof > 0)
        if not len(rows):
            return self.inconsistent
        slot = self.head[rows]
        self.ring[rows, slot], self.ring_dof[rows, slot] = nis[rows], dof[rows]
        self.head[rows] = (slot + 1) % self.window
        self.nis[rows] = self.ring[rows].sum(1)
        self.dof[rows] = self.ring_dof[rows].sum(1)
        self.updates[rows] = (self.ring_dof[rows] > 0).sum(1)
        self.inconsistent[rows] = self.nis[rows] > self.bounds[self.dof[rows]]
        return self.inconsistent

    def clear(self, rows: np.ndarray) -> None:
        """Start a new window for ``rows`` (G,) bool (after :func:`widen`: the innovations
        it holds were those of the covariance before)."""
        self.ring[rows], self.ring_dof[rows], self.head[rows] = 0.0, 0, 0

    def reason(self, g: int) -> str | None:
        """Why trajectory g's current estimate is flagged (:func:`describe`); None if not."""
        if not self.inconsistent[g]:
            return None
        return describe(float(self.nis[g]), int(self.dof[g]), int(self.updates[g]),
                        self.significance)

    def record(self, checks: Checks, k: int | slice) -> None:
        """Write the last test into row(s) ``k`` of a batch's :class:`Checks`."""
        for out, now in zip(checks, (self.inconsistent, self.nis, self.dof, self.updates)):
            out[:, k] = now[:, None] if isinstance(k, slice) else now

    def excess(self) -> np.ndarray:
        """(G,) the window's NIS per degree of freedom (1 where none): how many times larger
        its innovations' squares were than the covariance said."""
        return np.where(self.dof > 0, self.nis / np.maximum(self.dof, 1), 1.0)


def widen(P: np.ndarray, states: tuple[int, ...], factor: np.ndarray, rows: np.ndarray
          ) -> np.ndarray:
    """P (G, n, n) with the variances of ``states`` times ``factor`` (G,) in ``rows`` (G,)
    bool: ``D P D`` with ``D`` their square root on those states and 1 elsewhere, so P stays
    symmetric and positive semi-definite, and the states' correlations stay as they were."""
    scale = np.ones(P.shape[:2])
    root = np.sqrt(np.maximum(factor[rows], 1.0))  # never narrowed
    scale[np.ix_(np.flatnonzero(rows), np.array(states))] = root[:, None]
    return P * scale[:, :, None] * scale[:, None, :]
