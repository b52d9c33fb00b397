"""The one measurement update of the classical filters: Joseph form, per step, per channel.

Every stepper (:class:`~lbo.filters.kalman.KalmanStepper` for the EKF, the oracle and the
Sage-Husa adaptive EKF, :class:`~lbo.filters.unscented.UnscentedStepper`,
:class:`~lbo.filters.dynamic_ekf.DynamicStepper`) predicts in its own way and then calls
:func:`joseph_update` with the measurement model of the row at hand. A log row holds any
allowed subset of the measured channels ``[x_m, y_m, psi_m]``: a full fix, a position
without a heading, or nothing (a prediction step). The contract a stepper fulfils:

- the prior ``x`` (G, n) and ``P`` (G, n, n) of this step;
- the innovation ``y`` (G, p) = measurement minus predicted measurement, angles wrapped to
  (-pi, pi] by the stepper (it knows which channels are angles); any value (NaN included)
  where a channel is not held;
- the measurement Jacobian ``H`` (p, n) or (G, p, n) of all p channels, and their covariance
  ``R`` (p, p) or (G, p, p);
- ``held`` (G, p) bool: which channels this row holds (:func:`held_channels`).

A channel not held contributes nothing: its row of H, its innovation and its off-diagonal
covariances are zeroed and its variance set to 1, so that S is block diagonal with a 1 there
and the gain's column for it is exactly 0. The result is the update with the held channels
alone (tested against the subset update and a hand-written filter to 1e-12), with fixed
shapes, so G trajectories holding different subsets update in one vectorised call. A row
holding nothing leaves the prior unchanged (K = 0).

The update is Joseph's, ``P+ = (I - K H) P (I - K H)^T + K R K^T``, symmetrised: it stays
symmetric and positive semi-definite whatever the rounding, and is filterpy's (the EKF's
reference) for a full fix. It returns an :class:`Update`: the posterior, and the innovation
and its covariance S as the update used them, from which :func:`nis` gives each row's
normalised innovation squared ``y^T S^-1 y`` of the held channels that are ``tested``:
chi-square with as many degrees of freedom as those channels while the filter's covariance
explains its innovations (:mod:`lbo.filters.consistency` tests it).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from lbo.core.errors import LboError


@functools.cache
def _eye(n: int) -> np.ndarray:
    """The (n, n) identity, made once (this runs at every step of every filter)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def held_channels(m: np.ndarray) -> np.ndarray:
    """Which channels each row of ``m`` (G, p) holds: (G, p) bool, True where finite."""
    return np.isfinite(m)


class Update(NamedTuple):
    """One measurement update of G filters with p channels and n states."""

    x: np.ndarray
    """(G, n) posterior mean."""
    P: np.ndarray
    """(G, n, n) posterior covariance (Joseph form, symmetrised)."""
    y: np.ndarray
    """(G, p) innovation as the update took it: 0 where a channel is not held."""
    S: np.ndarray
    """(G, p, p) innovation covariance ``H P H^T + R`` of the held channels, with a unit
    variance and no correlation where a channel is not held."""


def joseph_update(x: np.ndarray, P: np.ndarray, y: np.ndarray, H: np.ndarray, R: np.ndarray,
                  held: np.ndarray) -> Update:
    """Kalman measurement update of G priors with the channels each row holds.

    Parameters
    ----------
    x : (G, n) prior mean.
    P : (G, n, n) prior covariance.
    y : (G, p) innovation, angles already wrapped; ignored where not ``held``.
    H : (p, n) or (G, p, n) measurement Jacobian of all p channels.
    R : (p, p) or (G, p, p) measurement covariance of all p channels.
    held : (G, p) bool, the channels this step's row holds.

    Returns
    -------
    The :class:`Update`: posterior mean and covariance, and the innovation and its covariance
    as taken (for :func:`nis`).
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    g, n = x.shape
    held = np.asarray(held, dtype=bool)
    p = held.shape[-1]
    if held.shape != (g, p) or np.shape(y) != (g, p) or P.shape != (g, n, n):
        raise LboError(f"joseph_update needs x (G, n), P (G, n, n), y and held (G, p); got "
                       f"{x.shape}, {P.shape}, {np.shape(y)}, {held.shape}")
    if np.shape(H) not in ((p, n), (g, p, n)) or np.shape(R) not in ((p, p), (g, p, p)):
        raise LboError(f"joseph_update needs H (p, n) or (G, p, n) and R (p, p) or (G, p, p) "
                       f"with p={p}, n={n}; got {np.shape(H)}, {np.shape(R)}")
    if not held.any():
        # a prediction step in every trajectory (most rows of a log between its fixes): K = 0,
        # and the full update below gives exactly this; skipped for its cost
        P = 0.5 * (P + P.swapaxes(-1, -2))
        return Update(x, P, np.zeros((g, p)), np.broadcast_to(_eye(p), (g, p, p)))
    # a channel not held: no row of H, no innovation, uncorrelated with a unit variance, so
    # S is block diagonal and that channel's column of K is exactly zero (np.where broadcasts
    # a shared H and R over the G rows)
    y = np.where(held, y, 0.0)
    H = np.where(held[..., None], H, 0.0)
    both = held[:, :, None] & held[:, None, :]
    R = np.where(both, R, _eye(p))
    PHt = P @ H.swapaxes(-1, -2)                                    # (G, n, p)
    S = H @ PHt + R                                                 # (G, p, p)
    K = np.linalg.solve(S, PHt.swapaxes(-1, -2)).swapaxes(-1, -2)   # P H^T S^-1, S symmetric
    I_KH = _eye(n) - K @ H
    post = I_KH @ P @ I_KH.swapaxes(-1, -2) + K @ R @ K.swapaxes(-1, -2)
    return Update(x + np.einsum("gij,gj->gi", K, y), 0.5 * (post + post.swapaxes(-1, -2)), y, S)


def nis(update: Update, held: np.ndarray, tested: np.ndarray | None = None) -> np.ndarray:
    """Each row's normalised innovation squared ``y^T S^-1 y`` (G,) over the channels it
    held (``held`` (G, p) bool) that are ``tested`` ((p,) or (G, p) bool; None: all), from the
    innovation and S of ``update``; 0 where a row holds none of them.

    S is the tested channels' block, the others set apart as the untaken ones are in
    :func:`joseph_update`: their innovations' marginal covariance, whatever the other channels
    of the row say."""
    held = np.asarray(held, dtype=bool)
    g, p = held.shape
    t = held if tested is None else held & np.asarray(tested, dtype=bool)
    if not t.any():  # nothing tested in any row (a standstill's zero rate alone)
        return np.zeros(g)
    S_t = np.where(t[:, :, None] & t[:, None, :], update.S, _eye(p))
    y_t = np.where(t, update.y, 0.0)
    return np.einsum("gp,gp->g", y_t, np.linalg.solve(S_t, y_t[..., None])[..., 0])
