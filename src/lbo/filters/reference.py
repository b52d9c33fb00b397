"""The paper's filters on filterpy, one trajectory at a time: the references.

:class:`BicycleEKF` / :func:`run_filterpy_ekf` are the paper's EKF, :func:`ukf` /
:func:`ukf_filterpy_batch` filterpy's unscented filter on the same model. They take full fixes
only (H = I), and are the slow loops that the vectorised steppers
(:mod:`lbo.filters.kalman`, :mod:`lbo.filters.unscented`) are tested and benchmarked against.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from tqdm.auto import tqdm

from lbo.core.angles import wrap_angle
from lbo.filters.start import batch_cov, check_q, check_trajectories, floor_diag
from lbo.filters.unscented import UKF_SPREAD
from lbo.sim.vehicle import Vehicle, jacobian, step

_I3 = np.eye(3)


def _residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a - b`` over the leading axis [x, y, psi] with the heading difference wrapped."""
    d = np.subtract(a, b)
    d[2] = wrap_angle(d[2])
    return d



class BicycleEKF(ExtendedKalmanFilter):
    """The paper's EKF: filterpy's ExtendedKalmanFilter with the bicycle step as prediction.

    Parameters
    ----------
    vehicle : Vehicle
        Supplies ``dt`` and ``wheelbase``.
    Q : (3, 3) process covariance.
    R : (3, 3) measurement covariance.

    Attributes
    ----------
    x : (3, 1) state estimate ``[x, y, psi]``; psi continuous.
    P : (3, 3) state covariance.
    F : (3, 3) Jacobian of the last prediction, evaluated at the state it started from.
    Q, R : (3, 3) process and measurement covariances (public, as in filterpy).
    """

    x: np.ndarray  # filterpy's, untyped

    def __init__(self, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray) -> None:
        super().__init__(dim_x=3, dim_z=3)
        self.vehicle = vehicle
        self.Q = check_q(Q).copy()
        self.R = np.asarray(R, dtype=float).copy()

    def predict_x(self, u: np.ndarray = 0) -> None:  # type: ignore[assignment]  # filterpy's u=0
        """Bicycle step ``z + f(z, u) dt``; u: (2,) ``[V, delta]``.

        Also sets ``F`` at the pre-step state, which filterpy's ``predict`` then uses for P.
        """
        z = self.x[:, 0]
        self.F = jacobian(z, u, self.vehicle.dt)
        self.x = step(z, u, self.vehicle.dt, self.vehicle.wheelbase)[:, None]

    @staticmethod
    def residual(z: np.ndarray, hx: np.ndarray) -> np.ndarray:
        """Innovation ``z - hx`` with the heading wrapped to (-pi, pi]. (3, 1) -> (3, 1)."""
        return _residual(z, hx)

    def update(self, z, HJacobian=None, Hx=None, R=None, args=(), hx_args=(), residual=None):
        """filterpy's update with H = I, h(x) = x and :meth:`residual` as defaults.

        z : (3,) or (3, 1) measurement ``[x_m, y_m, psi_m]``.
        """
        super().update(
            np.reshape(z, (3, 1)),
            HJacobian if HJacobian is not None else (lambda x: _I3),
            Hx if Hx is not None else (lambda x: x),
            R=R, args=args, hx_args=hx_args,
            residual=residual if residual is not None else self.residual,
        )


def run_filterpy_ekf(m: np.ndarray, u: np.ndarray, vehicle: Vehicle,
                     Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Run :class:`BicycleEKF` over one trajectory: the slow reference loop.

    Parameters
    ----------
    m : (T, 3) measurements.
    u : (T, 2) inputs; ``u[k]`` moves ``z_k`` to ``z_{k+1}``.
    vehicle : Vehicle
    Q, R : (3, 3) process and measurement covariances.

    Returns
    -------
    (T, 3) filtered estimates; row 0 is ``m_0``.
    """
    m, u = check_trajectories(np.asarray(m)[None], np.asarray(u)[None], receiver=False)
    m, u = m[0], u[0]
    ekf = BicycleEKF(vehicle, Q, R)
    ekf.x = m[0][:, None].copy()
    ekf.P = floor_diag(ekf.R)
    est = np.empty_like(m)
    est[0] = m[0]
    for k in range(1, len(m)):
        ekf.predict(u[k - 1])
        ekf.update(m[k])
        est[k] = ekf.x[:, 0]
    return est



def _circular_mean(sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
    """Weighted mean of sigma points (2n+1, 3); psi by circular mean, kept on the branch of
    the first (central) sigma point so that the estimate stays continuous."""
    mean = Wm @ sigmas
    d = wrap_angle(sigmas[:, 2] - sigmas[0, 2])
    mean[2] = sigmas[0, 2] + np.arctan2(Wm @ np.sin(d), Wm @ np.cos(d))
    return mean


def ukf(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
        spread: float = UKF_SPREAD) -> np.ndarray:
    """Unscented Kalman filter (filterpy, Merwe scaled sigma points) over one trajectory.

    Same model, noise, initialisation and wrapped heading residuals as the EKF. R's
    diagonal is floored at :data:`COV_FLOOR` so the Cholesky factorisation of P survives
    alpha=0.

    Parameters
    ----------
    m : (T, 3) measurements.
    u : (T, 2) inputs.
    vehicle : Vehicle
    Q, R : (3, 3) process and measurement covariances.
    spread : Merwe's alpha (sigma-point spread); beta=2, kappa=0.

    Returns
    -------
    (T, 3) filtered estimates.
    """
    m, u = check_trajectories(np.asarray(m)[None], np.asarray(u)[None], receiver=False)
    m, u = m[0], u[0]
    dt, wheelbase = vehicle.dt, vehicle.wheelbase
    points = MerweScaledSigmaPoints(3, alpha=spread, beta=2.0, kappa=0.0, subtract=_residual)
    flt = UnscentedKalmanFilter(
        dim_x=3, dim_z=3, dt=dt, points=points,
        fx=lambda z, dt, u: step(z, u, dt, wheelbase), hx=lambda z: z,
        x_mean_fn=_circular_mean, z_mean_fn=_circular_mean,
        residual_x=_residual, residual_z=_residual,
    )
    flt.Q = check_q(Q).copy()
    flt.R = floor_diag(R)
    flt.x = m[0].copy()
    flt.P = flt.R.copy()
    est = np.empty_like(m)
    est[0] = m[0]
    for k in range(1, len(m)):
        flt.predict(u=u[k - 1])
        flt.update(m[k])
        est[k] = flt.x
    return est


def ukf_filterpy_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray,
                       R: np.ndarray, spread: float = UKF_SPREAD, progress: bool = False
                       ) -> np.ndarray:
    """:func:`ukf` over G trajectories, one after the other: filterpy's loop, the reference
    that :func:`lbo.filters.unscented.ukf_batch` is tested and benchmarked against.

    Shapes as :func:`lbo.filters.unscented.ukf_batch`; ``progress`` shows a tqdm bar.
    """
    m, u = check_trajectories(m, u, receiver=False)
    R = batch_cov(R, m.shape[0], "R")
    est = np.empty_like(m)
    for i in tqdm(range(m.shape[0]), desc="UKF (filterpy)", unit="traj", disable=not progress,
                  mininterval=2.0):
        est[i] = ukf(m[i], u[i], vehicle, Q, R[i], spread=spread)
    return est
