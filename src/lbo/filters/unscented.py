"""The unscented Kalman filter of the kinematic bicycle, vectorised over trajectories.

:func:`ukf_batch` loops over :class:`UnscentedStepper` (:mod:`lbo.filters.stepper`): the numbers
of filterpy's loop (:func:`lbo.filters.reference.ukf_filterpy_batch`) to rounding, with the
conventions of :mod:`lbo.filters.start`.
"""

from __future__ import annotations

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.filters import measure
from lbo.filters.start import (
    CourseStart,
    batch_cov,
    check_q,
    check_trajectories,
    floor_diag,
    start_state,
)
from lbo.filters.stepper import Posterior, run_stepper
from lbo.filters.update import joseph_update
from lbo.sim.vehicle import Vehicle, step

UKF_SPREAD = 0.1
"""Merwe's sigma-point spread of lbo's UKF (alpha of the scaled unscented transform)."""

def merwe_weights(n: int, spread: float, beta: float = 2.0,
                  kappa: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Merwe's scaled sigma-point weights, as filterpy: ``(Wm, Wc, lambda)``, each (2n+1,)."""
    lam = spread**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = lam / (n + lam) + (1.0 - spread**2 + beta)
    return wm, wc, lam


def _sigma_points(x: np.ndarray, P: np.ndarray, lam: float) -> np.ndarray:
    """(G, 3), (G, 3, 3) -> (G, 7, 3): x, then x + and - the rows of the upper Cholesky factor
    of (n + lambda) P, headings wrapped (filterpy's order, with the reference's wrapped
    difference as its ``subtract``)."""
    n = x.shape[-1]
    rows = np.linalg.cholesky((n + lam) * P).swapaxes(-1, -2)  # upper factor U: rows U[k]
    sig = np.concatenate([x[:, None], x[:, None] + rows, x[:, None] - rows], axis=1)
    sig[:, 1:, 2] = wrap_angle(sig[:, 1:, 2])
    return sig


def _batch_mean(sig: np.ndarray, wm: np.ndarray) -> np.ndarray:
    """:func:`_circular_mean` over G sets of sigma points (G, S, 3) -> (G, 3)."""
    mean = np.einsum("s,gsi->gi", wm, sig)
    d = wrap_angle(sig[:, :, 2] - sig[:, :1, 2])
    mean[:, 2] = sig[:, 0, 2] + np.arctan2(np.sin(d) @ wm, np.cos(d) @ wm)
    return mean


def _deviations(sig: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Sigma points minus their mean (G, S, 3), heading wrapped."""
    d = sig - mean[:, None]
    d[..., 2] = wrap_angle(d[..., 2])
    return d


class UnscentedStepper:
    """The UKF of :func:`ukf_batch` one time step per call, over G trajectories.

    The same sigma points (Merwe, beta=2, kappa=0, upper Cholesky factor, wrapped headings),
    weights and circular means as filterpy's :class:`~filterpy.kalman.UnscentedKalmanFilter`
    for the prediction. The measurement is linear (the channels a row holds, of the state
    itself), and the unscented transform of a linear map is exact: its update is the Kalman
    update, :func:`lbo.filters.update.joseph_update` as every stepper's (filterpy's
    ``P - K S K^T`` on sigma points redrawn from the prior is the same to rounding: 1e-9 over
    the test trajectories, tested). :func:`ukf_batch` loops over it and
    :class:`lbo.Observer` steps it one sample at a time, so streaming and batch agree.

    Parameters
    ----------
    m0 : (G, 3) first measurements (position fixes); the state starts there with P_0 = R
        (a NaN heading: as :class:`lbo.filters.kalman.KalmanStepper`).
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (G, 3, 3) measurement covariance (diagonal floored at :data:`COV_FLOOR`).
    spread : Merwe's alpha.

    Attributes
    ----------
    x : (G, 3) current estimate. P : (G, 3, 3) its covariance.
    prior, cross, course : as :class:`lbo.filters.kalman.KalmanStepper`'s.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray, *,
                 spread: float = UKF_SPREAD) -> None:
        self.vehicle, self.Q = vehicle, check_q(Q)
        self.R = floor_diag(R)
        self.wm, self.wc, self.lam = merwe_weights(3, spread)
        self.x, self.P = start_state(m0, self.R)
        self.course = CourseStart(m0, vehicle, self.Q)

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with u_{k-1} (G, 2), update with what row m_k (G, 3) or (G, 8) holds (NaN
        channels are not measured, :mod:`lbo.filters.measure`); returns x_k (G, 3)."""
        m = measure.widen(m)
        wm, wc, lam = self.wm, self.wc, self.lam
        # predict: sigma points through the bicycle step, unscented transform plus Q
        before = _sigma_points(self.x, self.P, lam)
        sig = step(before, np.broadcast_to(u_prev[:, None], before.shape[:2] + (2,)),
                   self.vehicle.dt, self.vehicle.wheelbase)
        x = _batch_mean(sig, wm)
        d = _deviations(sig, x)
        P = np.einsum("s,gsi,gsj->gij", wc, d, d) + self.Q
        # cov(x_{k-1|k-1}, x_{k|k-1}) from the sigma points, for the URTS smoother
        cross = np.einsum("s,gsi,gsj->gij", wc, _deviations(before, self.x), d)
        self.course.advance(u_prev)
        R = measure.step_cov(m, self.R)
        m, R, P, start = self.course.take(m, 0.5 * (R[:, 0, 0] + R[:, 1, 1]), P, R)
        cross[start, :, 2] = 0.0  # the flat heading prior owes nothing to the past state
        self.cross = cross
        self.prior = (x, P)
        self.x, self.P, *_ = joseph_update(x, P, *measure.model(m, x, R))
        return self.x


def ukf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
              spread: float = UKF_SPREAD, progress: bool = False, smooth: bool = False,
              lengths: np.ndarray | None = None) -> Posterior:
    """:func:`lbo.filters.reference.ukf` vectorised over G trajectories (a loop over time
    only, of :class:`UnscentedStepper`): the numbers of
    :func:`lbo.filters.reference.ukf_filterpy_batch` to rounding.

    Parameters
    ----------
    m : (G, T, 3) measurements.
    u : (G, T, 2) inputs.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (3, 3) shared or (G, 3, 3) per trajectory.
    spread : Merwe's alpha.
    progress : show a tqdm bar over the time steps.
    smooth : the unscented RTS smoother's estimates instead (:mod:`lbo.filters.smoother`).

    Returns
    -------
    Posterior
        ``mean`` (G, T, 3) the filtered (or smoothed) estimates, ``cov`` (G, T, 3, 3).
    """
    m, u = check_trajectories(m, u)
    flt = UnscentedStepper(m[:, 0], vehicle, Q, batch_cov(R, m.shape[0], "R"), spread=spread)
    return run_stepper(flt, m, u, smooth=smooth,
                       progress="UKF" if progress else None, lengths=lengths)
